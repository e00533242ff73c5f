"""WorldModelTrainer: trains the video prediction model on play-data windows."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase

from dorp_rl.checkpoint import load_module_state
from dorp_rl.config import Choice, Float, Int, Nested, Text, checked
from dorp_rl.data import (
    play_segment_length,
)
from dorp_rl.envs import DiscreteActions
from dorp_rl.integrity import IntegrityError
from dorp_rl.metrics.world_model import open_loop_accuracy
from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel, palette_from_frames
from dorp_rl.objectives.video import FEEDBACK_MODES, VideoPredictionLoss
from dorp_rl.trainers.base import TrainerConfig, read_trained
from dorp_rl.trainers.windows import WindowTrainer
from dorp_rl.validation import check_device

#: Flat fields of older world-model configs that now live in ``model``.
_FLAT_MODEL_FIELDS = ("model_preset", "latent_dim", "prior")


@dataclass
class WorldModelConfig(TrainerConfig):
    """Everything that defines a world-model run: env and play data, video model, loss.

    Play data are random-action trajectories of ``trajectory_length`` steps (for
    rearrangement a fresh random configuration starts each one); the model trains on
    windows of ``horizon`` steps. The open-loop length (steps the model feeds on its own
    predictions before restarting from the true frame) grows linearly from 1 to
    ``horizon`` over the first ``open_loop_ramp`` share of the steps: pure one-step
    training first, full open-loop rollouts after. With ``event_share > 0`` at least that
    share of the windows holds an *event*, a transition that changes more cells than an
    ordinary step (:class:`~dorp_rl.data.EventWindowSampler`): random play in key-wall
    takes the key in about 0.1% of its transitions, too rare in uniform windows for a
    model to learn that the door opens. Configs stored without the field read as 0
    (uniform windows).

    Use :meth:`rearrangement`, :meth:`key_wall` or :meth:`key_corridor`, then override
    fields with :meth:`replace` (``cfg.replace(model=VideoModelConfig.small())`` or
    ``cfg.replace(model={"latent_dim": 0})``). Configs stored by older versions, with
    flat ``model_preset``, ``latent_dim`` and ``prior`` fields, are read into ``model``.
    """

    default_num_objects = 3

    trajectory_length: int = checked(16, Int(low=1))
    """steps per play trajectory"""
    out_dir: str = checked("outputs/world_model", Text())
    """folder of checkpoints and logs"""
    # windows and evaluation
    horizon: int = checked(14, Int(low=1))
    """steps per training window"""
    event_share: float = checked(
        0.0,
        Float(
            low=0.0,
            high=1.0,
            high_open=True,
            hint="(a share of the training windows: 0 keeps them uniform, 1 would train on "
            "event windows only)",
        ),
    )
    """least share of training windows holding a rare event, e.g. the key taken (0: uniform)"""
    eval_frames: int = checked(8_000, Int(low=1))
    """held-out play transitions for evaluation"""
    eval_sequences: int = checked(512, Int(low=1))
    """held-out windows the open-loop accuracy is measured on"""
    eval_every: int = checked(1000, Int(low=1))
    """steps between evaluations"""
    # model
    model: VideoModelConfig = checked(
        rule=Nested(VideoModelConfig, default=VideoModelConfig.default)
    )
    """the video model (VideoModelConfig.small() is about 4x smaller)"""
    # loss
    feedback: str = checked("straight_through", Choice(FEEDBACK_MODES))
    """how predictions are fed back: straight_through, soft or hard"""
    kl_weight: float = checked(1.0, Float(low=0.0))
    """weight of the KL term"""
    free_bits: float = checked(0.0, Float(low=0.0))
    """KL free bits"""
    deterministic_fraction: float = checked(0.5, Float(low=0.0, high=1.0))
    """share of steps trained with z at its mean"""
    open_loop_ramp: float = checked(0.5, Float(low=0.0, high=1.0))
    """share of the steps over which the open-loop length grows to horizon"""
    # optimisation
    batch_size: int = checked(32, Int(low=1))
    """windows per step"""
    lr: float = checked(2e-3, Float(low=0.0, low_open=True, hint="(0 would never change a weight)"))
    """Adam learning rate at the start"""
    lr_final: float = checked(1e-4, Float(low=0.0))
    """learning rate at the end of the cosine decay"""
    grad_clip: float = checked(
        1.0,
        Float(
            low=0.0,
            low_open=True,
            allow_inf=True,
            hint="(0 would freeze every weight; math.inf turns clipping off)",
        ),
    )
    """gradient-norm clip (inf: off)"""
    num_steps: int = checked(6000, Int(low=1))
    """training steps"""

    @classmethod
    def profile_overrides(cls, profile: Any, num_objects: int) -> dict[str, Any]:
        """The env profile's world-model preset (:attr:`~dorp_rl.envs.EnvProfile.world_model`)."""
        return profile.world_model_overrides(num_objects)

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Older flat configs: ``model_preset``, ``latent_dim`` and ``prior`` become ``model``."""
        values = super().upgrade(values)
        flat = cls.pop_flat_fields(values, _FLAT_MODEL_FIELDS, "model")
        if flat:
            preset = flat.pop("model_preset", "default")
            values["model"] = VideoModelConfig.preset(preset, **flat).to_dict()
        return values

    def check_relations(self) -> None:
        """Rules between fields; each message names the fields and what they allow."""
        super().check_relations()
        if self.trajectory_length < self.horizon:
            raise ValueError(
                f"trajectory_length ({self.trajectory_length}) must be >= horizon "
                f"({self.horizon}): windows never cross a trajectory boundary."
            )
        for name, what in (
            ("num_frames", "training play data"),
            ("eval_frames", "held-out play data"),
        ):
            frames = getattr(self, name)
            if play_segment_length(frames, self.num_envs, self.trajectory_length) < self.horizon:
                least = (self.horizon - 1) * self.num_envs + 1
                raise ValueError(
                    f"{name} ({frames}) must be at least {least} for windows of horizon "
                    f"{self.horizon}: the {what} are collected by num_envs={self.num_envs} envs "
                    f"side by side, each storing ceil({name} / num_envs) = "
                    f"{math.ceil(frames / self.num_envs)} consecutive steps of its trajectory, "
                    f"and a window needs {self.horizon} (or lower num_envs or horizon)."
                )

    def model_config(self) -> VideoModelConfig:
        """The video model this config trains (a copy of ``model``)."""
        return self.model.replace()


class WorldModelTrainer(WindowTrainer):
    """Trains a :class:`~dorp_rl.modules.VideoPredictionModel` with :class:`~dorp_rl.objectives.VideoPredictionLoss`.

    Play data (collected, or loaded from ``config.data_dir``) are sampled as windows of
    ``horizon`` steps by a :class:`~dorp_rl.data.SequenceSampler`; held-out play data
    from another seed give ``eval_sequences`` fixed windows on which
    :func:`~dorp_rl.metrics.world_model.open_loop_accuracy` is measured every
    ``eval_every`` steps and at the end. The palette is read off the play data. Adam
    with a cosine learning-rate decay from ``lr`` to ``lr_final`` and gradient-norm
    clipping. Logging, checkpoints and ``train(resume=True)`` follow
    :class:`~dorp_rl.trainers.OfflineTrainer`.

    Examples:
        >>> from dorp_rl.modules import VideoModelConfig
        >>> from dorp_rl.trainers import WorldModelConfig, WorldModelTrainer
        >>> cfg = WorldModelConfig.for_env("rearrangement", 1, num_steps=5, num_frames=640, horizon=3,
        ...     trajectory_length=4, eval_frames=256, eval_sequences=8, model=VideoModelConfig.small(),
        ...     progress=False, out_dir="/tmp/dorp_doc_world_model")
        >>> result = WorldModelTrainer(cfg).train()
        >>> result["step"], len(result["evaluation"]["exact_accuracy"])
        (5, 3)
    """

    kind = "world_model"
    progress_metric = "loss_reconstruction"

    def __init__(
        self,
        config: WorldModelConfig,
        buffer: TensorDictReplayBuffer | None = None,
        eval_buffer: TensorDictReplayBuffer | None = None,
        logger: Any | None = None,
    ) -> None:
        config.validate()
        env = config.make_env(batch_size=(config.num_envs,))
        super().__init__(config, env, buffer, eval_buffer, logger)
        palette = palette_from_frames(self.buffer[: min(len(self.buffer), 20_000)]["pixels"])
        self.model = VideoPredictionModel(
            DiscreteActions.of(self.env).num_actions, palette, config.model_config()
        ).to(self.device)
        self.loss = VideoPredictionLoss(
            self.model,
            open_loop_length=1,
            feedback=config.feedback,
            kl_weight=config.kl_weight,
            free_bits=config.free_bits,
            deterministic_fraction=config.deterministic_fraction,
        )
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        stored_model = WorldModelConfig.from_dict(stored).model_config()
        if stored_model != self.config.model_config():
            raise ValueError(
                f"checkpoint holds a video model with {stored_model}, this trainer builds "
                f"{self.config.model_config()}."
            )

    def evaluate(self) -> dict[str, Any]:
        """Open-loop accuracy on the held-out windows (deterministic mode)."""
        result = open_loop_accuracy(self.model, self.eval_windows)
        steps = sorted({1, (result["horizon"] + 1) // 2, result["horizon"]})
        for h in steps:
            result[f"exact_accuracy_step{h}"] = result["exact_accuracy"][h - 1]
        if self.eval_event_windows is not None:
            events = open_loop_accuracy(self.model, self.eval_event_windows)
            result["event_num_sequences"] = events["num_sequences"]
            for h in steps:
                result[f"event_exact_accuracy_step{h}"] = events["exact_accuracy"][h - 1]
        return result


def load_video_model(
    path: str | Path, env: EnvBase | None = None, device: str | torch.device = "cpu"
) -> VideoPredictionModel:
    """The trained video model of a world-model checkpoint, in eval mode.

    Args:
        path: a checkpoint written by :class:`WorldModelTrainer`.
        env: if given, the checkpoint must come from this environment.
        device: where to put the model.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a damaged, incomplete or non-finite file
            (:class:`~dorp_rl.integrity.IntegrityError`), another kind of checkpoint or
            another environment.
    """
    device = check_device(device)
    cfg, state, _ = read_trained(path, WorldModelTrainer.kind, WorldModelConfig, env, "model")
    if "palette" not in state:
        raise IntegrityError(f"checkpoint {path} is incomplete: its model has no 'palette'.")
    num_actions = DiscreteActions.of(cfg.make_env()).num_actions
    model = VideoPredictionModel(num_actions, state["palette"], cfg.model_config())
    load_module_state(model, state, path, "model")
    return model.to(device).eval()
