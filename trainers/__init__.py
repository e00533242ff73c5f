"""Trainers: RepresentationTrainer (codes), WorldModelTrainer (video model), their Trainer base."""

from dorp_rl.trainers.base import Trainer, TrainingDivergedError
from dorp_rl.trainers.representation import (
    ENV_NAMES,
    RepresentationConfig,
    RepresentationTrainer,
    diagnose,
    load_encoder,
)
from dorp_rl.trainers.world_model import WorldModelConfig, WorldModelTrainer, load_video_model

__all__ = [
    "ENV_NAMES",
    "RepresentationConfig",
    "RepresentationTrainer",
    "Trainer",
    "TrainingDivergedError",
    "WorldModelConfig",
    "WorldModelTrainer",
    "diagnose",
    "load_encoder",
    "load_video_model",
]
