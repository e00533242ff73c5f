"""Trainers: RepresentationTrainer (codes), WorldModelTrainer (video model),
LatentWorldModelTrainer (latent world model), their OfflineTrainer base.

Configs share :class:`TrainerConfig` (environment, play data, bookkeeping) and embed
their model's config (``RepresentationConfig.encoder``, ``WorldModelConfig.model``).
Behaviour around the loop (restarts, screening) lives in :class:`TrainerHook` objects
registered on the trainer, their state checkpointed with it.
"""

from dorp_rl.envs import ENV_NAMES
from dorp_rl.trainers.base import (
    NoCheckpointWarning,
    OfflineTrainer,
    TrainerConfig,
    TrainerHook,
    TrainingDivergedError,
    TrainingGaveUpError,
)
from dorp_rl.trainers.latent_world_model import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    load_latent_world_model,
    load_world_model,
)
from dorp_rl.trainers.representation import (
    CandidateScreening,
    CollapseRestart,
    DeadOneHotRestart,
    EntanglementRestart,
    RepresentationConfig,
    RepresentationTrainer,
    RestartHook,
    WidthOrder,
    choose_code_settings,
    diagnose,
    load_encoder,
)
from dorp_rl.trainers.world_model import WorldModelConfig, WorldModelTrainer, load_video_model

__all__ = [
    "ENV_NAMES",
    "CandidateScreening",
    "CollapseRestart",
    "DeadOneHotRestart",
    "EntanglementRestart",
    "LatentWorldModelConfig",
    "LatentWorldModelTrainer",
    "NoCheckpointWarning",
    "OfflineTrainer",
    "RepresentationConfig",
    "RepresentationTrainer",
    "RestartHook",
    "TrainerConfig",
    "TrainerHook",
    "TrainingDivergedError",
    "TrainingGaveUpError",
    "WidthOrder",
    "choose_code_settings",
    "WorldModelConfig",
    "WorldModelTrainer",
    "diagnose",
    "load_encoder",
    "load_latent_world_model",
    "load_world_model",
    "load_video_model",
]
