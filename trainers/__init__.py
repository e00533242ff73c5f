"""Trainers: RepresentationTrainer (codes), WorldModelTrainer (video model), their Trainer base."""

from dorp_rl.trainers.base import Trainer
from dorp_rl.trainers.representation import (
    ENV_NAMES,
    RepresentationConfig,
    RepresentationTrainer,
    diagnose,
)
from dorp_rl.trainers.world_model import WorldModelConfig, WorldModelTrainer

__all__ = [
    "ENV_NAMES",
    "RepresentationConfig",
    "RepresentationTrainer",
    "Trainer",
    "WorldModelConfig",
    "WorldModelTrainer",
    "diagnose",
]
