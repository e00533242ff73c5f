"""LatentWorldModelTrainer: trains a latent world model on play windows against a DORP
encoder's codes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import TensorDictReplayBuffer

from dorp_rl.checkpoint import load_checkpoint, load_module_state
from dorp_rl.config import Flag, Float, Int, Nested, Text, checked
from dorp_rl.data import SequenceSampler, play_segment_length, rare_code_changes
from dorp_rl.envs import DiscreteActions
from dorp_rl.frames import frame_shape_of
from dorp_rl.integrity import state_digest
from dorp_rl.metrics.world_model import latent_open_loop_accuracy
from dorp_rl.modules.encoder import choose_map_stride
from dorp_rl.modules.latent import LatentModelConfig, LatentWorldModel, check_latent_model
from dorp_rl.objectives.latent import LatentWorldModelLoss
from dorp_rl.trainers.base import TrainerConfig, read_trained
from dorp_rl.trainers.representation import load_encoder
from dorp_rl.trainers.windows import WindowTrainer
from dorp_rl.trainers.world_model import WorldModelTrainer, load_video_model
from dorp_rl.validation import check_device

__all__ = [
    "LatentWorldModelConfig",
    "LatentWorldModelTrainer",
    "load_latent_world_model",
    "load_world_model",
]


@dataclass
class LatentWorldModelConfig(TrainerConfig):
    """Everything that defines a latent world-model run: play windows, model, loss, codes.

    The model learns the codes of the DORP encoder of ``encoder_checkpoint`` (or of an
    encoder given to the trainer): the code head's logits at every imagined step against
    the encoder's codes of the true frame. Its ``frame_shape`` and ``code_sizes`` are
    taken from the env and the encoder. The open-loop length (steps between restarts
    from the encoded true frame) grows from 1 to ``horizon`` over the first
    ``open_loop_ramp`` share of the steps.

    Examples:
        >>> from dorp_rl.trainers import LatentWorldModelConfig
        >>> LatentWorldModelConfig.for_env("key-wall").trajectory_length
        1000
    """

    default_num_objects = 3

    trajectory_length: int = checked(16, Int(low=1))
    """steps per play trajectory"""
    out_dir: str = checked("outputs/latent_world_model", Text())
    """folder of checkpoints and logs"""
    encoder_checkpoint: str | None = checked(None, Text(optional=True))
    """the representation checkpoint whose codes the model learns (None: an encoder is
    given to the trainer)"""
    horizon: int = checked(14, Int(low=1))
    """steps per training window"""
    event_share: float | None = checked(
        None, Float(low=0.0, high=1.0, high_open=True, optional=True)
    )
    """least share of training windows holding a rare event: a change of the code of a
    one-hot whose code changes at most a quarter as often as the most changing one-hot's
    (the key taken, a door toggled); None: chosen by the trainer, 0.25 where the
    encoder's codes of the play data show such events, else 0"""
    eval_frames: int = checked(8_000, Int(low=1))
    """held-out play transitions for evaluation"""
    eval_sequences: int = checked(512, Int(low=1))
    """held-out windows the open-loop accuracy is measured on"""
    eval_every: int = checked(1000, Int(low=1))
    """steps between evaluations"""
    model: LatentModelConfig = checked(
        rule=Nested(LatentModelConfig, default=LatentModelConfig.recipe)
    )
    """the model (default :meth:`LatentModelConfig.recipe`; frame_shape and code_sizes are
    set from the env and the encoder)"""
    open_loop_ramp: float = checked(0.3, Float(low=0.0, high=1.0))
    """share of the steps over which the open-loop length grows to horizon"""
    pixel_weight: float = checked(10.0, Float(low=0.0))
    """weight of the decoded frames' squared error"""
    change_weight: float = checked(0.0, Float(low=0.0))
    """weight of the decoded frames' squared error at the values that changed since the
    step before (mean over those values): moves of a few pixels the whole frame's error
    barely sees"""
    pixel_steps: int | None = checked(None, Int(low=1, optional=True))
    """decode and score this many random steps of each window (None: every step of it;
    decoding is the largest part of a training step)"""
    latent_weight: float = checked(0.1, Float(low=0.0))
    """weight of the imagined latents' distance to the encoded true frames"""
    soft_targets: bool = checked(True, Flag())
    """train the code head on the encoder's code probabilities instead of its codes"""
    hard_weight: float = checked(0.0, Float(low=0.0))
    """with soft_targets, weight of a cross-entropy against the encoder's codes as well
    (where its probabilities are nearly tied, the head still learns which code wins)"""
    batch_size: int = checked(32, Int(low=1))
    """windows per step"""
    lr: float = checked(1e-3, Float(low=0.0, low_open=True, hint="(0 would never change a weight)"))
    """Adam learning rate at the start"""
    lr_final: float = checked(1e-4, Float(low=0.0))
    """learning rate at the end of the cosine decay"""
    grad_clip: float = checked(1.0, Float(low=0.0, low_open=True, allow_inf=True))
    """gradient-norm clip (inf: off)"""
    num_steps: int = checked(3000, Int(low=1))
    """training steps"""

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Stored configs of older versions keep the defaults they were trained with."""
        values = super().upgrade(values)
        for name, before in (("pixel_weight", 1.0), ("soft_targets", False), ("event_share", 0.0)):
            values.setdefault(name, before)
        if isinstance(values.get("model"), dict):  # fields stored before the recipe existed
            model = {
                "dynamics_kind": "mlp",
                "decoder_kind": "conv",
                "decoder_hidden": 256,
                "frame_stride": 1,
            }
            values["model"] = {**model, **values["model"]}
        return values

    @classmethod
    def profile_overrides(cls, profile: Any, num_objects: int) -> dict[str, Any]:
        """The profile's latent-model preset over the play-window fields of its
        world-model preset."""
        preset = profile.world_model_overrides(num_objects)
        shared = ("trajectory_length", "event_share", "num_frames", "horizon")
        windows = {k: v for k, v in preset.items() if k in shared}
        return {**windows, **profile.latent_model_overrides(num_objects)}

    def check_relations(self) -> None:
        super().check_relations()
        if self.trajectory_length < self.horizon:
            raise ValueError(
                f"trajectory_length ({self.trajectory_length}) must be >= horizon "
                f"({self.horizon}): windows never cross a trajectory boundary."
            )
        for name in ("num_frames", "eval_frames"):
            frames = getattr(self, name)
            if play_segment_length(frames, self.num_envs, self.trajectory_length) < self.horizon:
                least = (self.horizon - 1) * self.num_envs + 1
                raise ValueError(
                    f"{name} ({frames}) must be at least {least} for windows of horizon "
                    f"{self.horizon} collected by num_envs={self.num_envs} envs side by side."
                )


class LatentWorldModelTrainer(WindowTrainer):
    """Trains a :class:`~dorp_rl.modules.LatentWorldModel` with
    :class:`~dorp_rl.objectives.LatentWorldModelLoss`.

    Windows of ``horizon`` steps of play data (collected, or loaded from
    ``config.data_dir``); held-out play data from another seed give ``eval_sequences``
    windows on which :func:`~dorp_rl.metrics.latent_open_loop_accuracy` is measured every
    ``eval_every`` steps and at the end. Adam with a cosine decay from ``lr`` to
    ``lr_final``, gradient-norm clipping; logging, checkpoints and resume as every
    :class:`~dorp_rl.trainers.OfflineTrainer`.

    Args:
        config: the run.
        encoder: the DORP encoder whose codes are the targets (default: loaded from
            ``config.encoder_checkpoint``).
        buffer, eval_buffer: play data to use instead of collecting it.
        logger: a torchrl logger (default: CSV in ``out_dir``).

    Examples:
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.trainers import LatentWorldModelConfig, LatentWorldModelTrainer
        >>> codes = DiscreteCodeEncoder(EncoderConfig.small((16,)))
        >>> cfg = LatentWorldModelConfig.for_env("rearrangement", 1, num_steps=3, num_frames=640,
        ...     horizon=3, trajectory_length=4, eval_frames=256, eval_sequences=8, progress=False,
        ...     out_dir="/tmp/dorp_doc_latent_model")
        >>> result = LatentWorldModelTrainer(cfg, encoder=codes).train()
        >>> result["step"], len(result["evaluation"]["code_accuracy"])
        (3, 3)
    """

    kind = "latent_world_model"
    progress_metric = "loss_code"

    def __init__(
        self,
        config: LatentWorldModelConfig,
        encoder: nn.Module | None = None,
        buffer: TensorDictReplayBuffer | None = None,
        eval_buffer: TensorDictReplayBuffer | None = None,
        logger: Any | None = None,
    ) -> None:
        config.validate()
        env = config.make_env(batch_size=(config.num_envs,))
        if encoder is None:
            if config.encoder_checkpoint is None:
                raise ValueError(
                    "LatentWorldModelTrainer needs the DORP encoder whose codes it learns: "
                    "pass encoder= or set encoder_checkpoint."
                )
            encoder = load_encoder(config.encoder_checkpoint, env)
        frame_shape = frame_shape_of(env)
        stride = config.model.frame_stride
        if stride is None:  # the encoder's map stride (its smallest piece counted), or by size
            stride = getattr(encoder, "map_stride", None) or choose_map_stride(frame_shape)
        config = config.replace(
            model={
                "frame_shape": frame_shape,
                "code_sizes": tuple(encoder.code_sizes),
                "encoder_digest": state_digest(encoder),
                # the frame size decides it; written to the checkpoint's config
                "frame_stride": int(stride),
            }
        )
        super().__init__(config, env, buffer, eval_buffer, logger)
        self.encoder = encoder.to(self.device).eval()
        self.model = LatentWorldModel(
            DiscreteActions.of(self.env).num_actions, config.model.replace()
        ).to(self.device)
        self.loss = LatentWorldModelLoss(
            self.model,
            self.encoder,
            open_loop_length=1,
            pixel_weight=config.pixel_weight,
            latent_weight=config.latent_weight,
            soft_targets=config.soft_targets,
            hard_weight=config.hard_weight,
            change_weight=config.change_weight,
            pixel_steps=config.pixel_steps,
        )
        self.actions = DiscreteActions.of(self.env)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        # The encoder's codes (and, for soft targets, probabilities) of every stored
        # frame, once: each batch's targets are looked up by the sampled indices
        # instead of encoding 2 x H frames per window.
        self.target_tables = self._encode_storage()
        #: the settings chosen from the env's data: field -> {"value", "why"}
        self.chosen: dict[str, dict[str, Any]] = {}
        if self.config.event_share is None:
            self._choose_event_share()

    def training_sampler(self) -> SequenceSampler:
        """Uniform windows until :attr:`config.event_share` is chosen, then as configured."""
        if self.config.event_share is None:
            return SequenceSampler(self.config.horizon)
        return super().training_sampler()

    def _choose_event_share(self) -> None:
        """``event_share``: 0.25 where the codes of the play data show rare events, else 0."""
        events = self.transition_events(self.buffer.storage)
        found = int(events.sum())
        share = 0.25 if found else 0.0
        self.config = self.config.replace(event_share=share)
        why = (
            f"{found} of {events.numel()} play transitions change a rarely changing one-hot's "
            "code: a quarter of the windows hold one"
            if found
            else "no one-hot's code changes rarely in the play data"
        )
        self.chosen["event_share"] = {"value": share, "why": why}
        self.logger.log_hparams({"chosen.event_share": f"{share} ({why})"})
        if share:
            self.buffer.set_sampler(self.training_sampler())
            self.buffer.set_rng(self.data_generator)

    def _encode_storage(
        self, storage: Any = None, *, probs: bool | None = None, chunk: int = 4096
    ) -> dict[Any, torch.Tensor]:
        """Targets of every transition of ``storage`` (default: the training buffer's), by
        the batch key they fill: codes int64 ``[N, K]`` of ``pixels`` and ``("next",
        "pixels")`` under ``code`` and ``("next", "code")``, and with ``probs`` (default:
        ``soft_targets``) their probabilities ``[N, K, Z]`` under ``code_probs`` and
        ``("next", "code_probs")``."""
        storage = self.buffer.storage if storage is None else storage
        probs = self.config.soft_targets if probs is None else probs
        keys = self.loss.tensor_keys
        tables: dict[Any, torch.Tensor] = {}
        for frames_key, code_key, probs_key in (
            ("pixels", keys.code, keys.code_probs),
            (("next", "pixels"), keys.next_code, keys.next_code_probs),
        ):
            codes, probabilities = [], []
            for start in range(0, len(storage), chunk):
                rows = storage[start : min(len(storage), start + chunk)]
                code, prob = self.loss.encode_targets(rows.get(frames_key).to(self.device))
                codes.append(code.to(torch.int64))
                if probs:
                    probabilities.append(prob)
            tables[code_key] = torch.cat(codes)
            if probabilities:
                tables[probs_key] = torch.cat(probabilities)
        return tables

    def transition_events(self, storage: Any) -> torch.Tensor:
        """The transitions changing the code of a one-hot whose code rarely changes
        (:func:`~dorp_rl.data.rare_code_changes`), by the encoder's codes: the events a
        code head must learn (a door toggled in MiniGrid changes fewer cells than an
        agent's move, so counting cells misses it)."""
        keys = self.loss.tensor_keys
        tables = (
            self.target_tables
            if storage is self.buffer.storage
            else self._encode_storage(storage, probs=False)
        )
        return rare_code_changes(tables[keys.code].cpu(), tables[keys.next_code].cpu())

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        stored_model = LatentWorldModelConfig.from_dict(stored).model
        if stored_model != self.config.model:
            raise ValueError(
                f"checkpoint holds a latent world model with {stored_model}, this trainer "
                f"builds {self.config.model}."
            )

    def _index_actions(self, batch: TensorDictBase) -> TensorDictBase:
        """Play actions in the env's layout (one-hot or index) as int64 indices ``[B, H, 1]``."""
        return batch.set("action", self.actions.index(batch.get("action")))

    def training_batch(self) -> TensorDictBase:
        """Training windows with int64 action indices and the looked-up targets."""
        batch = self._index_actions(super().training_batch())
        for key, table in self.target_tables.items():
            batch.set(key, table[batch.get("index").to(table.device)].to(self.device))
        return batch

    def train_step(self) -> dict[str, float]:
        metrics = super().train_step()
        metrics["open_loop_length"] = float(self.loss.open_loop_length)
        return metrics

    def evaluate(self) -> dict[str, Any]:
        """Open-loop code (and decoded pixel) accuracy on the held-out windows."""
        windows = self._index_actions(self.eval_windows.clone())
        result = latent_open_loop_accuracy(self.model, self.encoder, windows)
        steps = sorted({1, (result["horizon"] + 1) // 2, result["horizon"]})
        for h in steps:
            result[f"code_accuracy_step{h}"] = result["code_accuracy"][h - 1]
        if self.eval_event_windows is not None:
            events = self._index_actions(self.eval_event_windows.clone())
            events = latent_open_loop_accuracy(self.model, self.encoder, events)
            result["event_num_sequences"] = events["num_sequences"]
            for h in steps:
                result[f"event_code_accuracy_step{h}"] = events["code_accuracy"][h - 1]
        return result


def load_latent_world_model(
    path: str | Path,
    env: Any | None = None,
    encoder: nn.Module | None = None,
    device: str | torch.device = "cpu",
) -> LatentWorldModel:
    """The trained latent world model of a checkpoint, in eval mode.

    Args:
        path: a checkpoint written by :class:`LatentWorldModelTrainer`.
        env: if given, the checkpoint must come from this environment.
        encoder: if given, the model must predict this encoder's code sizes and frames.
        device: where to put the model.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a damaged or incomplete file, another kind of checkpoint, another
            environment, or other code sizes or frames than ``encoder``'s.
    """
    device = check_device(device)
    kind = LatentWorldModelTrainer.kind
    cfg, state, payload = read_trained(path, kind, LatentWorldModelConfig, env, "model")
    num_actions = DiscreteActions.of(cfg.make_env() if env is None else env).num_actions
    model = LatentWorldModel(num_actions, cfg.model)
    load_module_state(model, state, path, "model")
    if encoder is not None:
        check_latent_model(
            model, encoder.code_sizes, getattr(encoder, "frame_shape", model.frame_shape)
        )
    return model.to(device).eval()


def load_world_model(
    path: str | Path, env: Any | None = None, device: str | torch.device = "cpu"
) -> nn.Module:
    """The world model of a checkpoint of either kind: a latent world model
    (:class:`LatentWorldModelTrainer`) or a palette video model
    (:class:`~dorp_rl.trainers.WorldModelTrainer`), checked against ``env``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a damaged file, a checkpoint of another kind (codes, say) or of
            another environment.
    """
    kinds = {WorldModelTrainer.kind: load_video_model}
    kinds[LatentWorldModelTrainer.kind] = load_latent_world_model
    kind = load_checkpoint(path).get("kind")
    if kind not in kinds:
        raise ValueError(
            f"checkpoint {path} holds a {kind!r} model, expected {WorldModelTrainer.kind!r} "
            f"(a video model) or {LatentWorldModelTrainer.kind!r}."
        )
    return kinds[kind](path, env, device=device)
