"""Trainers: RepresentationTrainer (codes); WorldModelTrainer comes with the video model."""

from dorp_rl.trainers.representation import (
    ENV_NAMES,
    RepresentationConfig,
    RepresentationTrainer,
    diagnose,
)

__all__ = ["ENV_NAMES", "RepresentationConfig", "RepresentationTrainer", "diagnose"]
