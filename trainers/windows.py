"""WindowTrainer: what the world-model trainers share: play windows, schedules, the step."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase

from dorp_rl.checkpoint import load_module_state
from dorp_rl.data import (
    EventWindowSampler,
    SequenceSampler,
    changed_pixels,
    check_play_buffer,
    collect_play_data,
    event_transitions,
)
from dorp_rl.trainers.base import OfflineTrainer
from dorp_rl.validation import derive_seed

__all__ = ["HELD_OUT_SEED_OFFSET", "WindowTrainer", "event_windows"]

#: seed offset of the held-out play data used for evaluation
HELD_OUT_SEED_OFFSET = 100_003


class WindowTrainer(OfflineTrainer):
    """Base of trainers of models that roll out over ``horizon``-step play windows.

    Play data (collected, or loaded from ``config.data_dir``) are sampled as windows by
    a :class:`~dorp_rl.data.SequenceSampler` (or an
    :class:`~dorp_rl.data.EventWindowSampler` with ``config.event_share > 0``); held-out
    play data of another seed give ``eval_sequences`` fixed windows (and the windows
    among them holding an event). The open-loop length grows from 1 to ``horizon`` over
    the first ``open_loop_ramp`` share of the steps; Adam with a cosine decay from ``lr``
    to ``lr_final`` and gradient-norm clipping. A subclass sets ``self.model``,
    ``self.loss`` (with an ``open_loop_length``) and ``self.optimizer``, and may add to
    each training batch (:meth:`training_batch`).
    """

    state_keys = ("model", "optimizer")

    def __init__(
        self,
        config: Any,
        env: EnvBase,
        buffer: TensorDictReplayBuffer | None,
        eval_buffer: TensorDictReplayBuffer | None,
        logger: Any | None,
    ) -> None:
        super().__init__(config, env, logger)
        self.device = torch.device(config.device)
        for name, given in (("buffer", buffer), ("eval_buffer", eval_buffer)):
            if given is not None:
                check_play_buffer(given, self.env, min_trajectory_length=config.horizon, name=name)
                given.set_sampler(
                    self.training_sampler() if name == "buffer" else SequenceSampler(config.horizon)
                )
        if buffer is None:
            buffer = collect_play_data(
                self.env,
                config.num_frames,
                directory=config.data_dir,
                seed=config.seed,
                trajectory_length=config.trajectory_length,
                sampler=self.training_sampler(),
                batch_size=config.batch_size,
                progress=config.progress,
            )
        if eval_buffer is None:
            eval_buffer = collect_play_data(
                self.env,
                config.eval_frames,
                seed=derive_seed(config.seed, HELD_OUT_SEED_OFFSET),
                trajectory_length=config.trajectory_length,
                sampler=SequenceSampler(config.horizon),
            )
        self.buffer = buffer
        self.buffer.set_rng(self.data_generator)
        eval_generator = torch.Generator().manual_seed(config.seed)
        eval_buffer.set_rng(eval_generator)
        self.eval_windows: TensorDictBase = eval_buffer.sample(config.eval_sequences)
        self._eval_buffer = eval_buffer
        self._eval_event_windows: TensorDictBase | None | bool = False  # False: not yet
        torch.manual_seed(config.seed)
        self.data_generator.manual_seed(derive_seed(config.seed, 1))

    def training_sampler(self) -> SequenceSampler:
        """Training windows: uniform, or with ``event_share`` of them holding an event
        (:meth:`transition_events`)."""
        cfg = self.config
        if cfg.event_share > 0:
            return EventWindowSampler(cfg.horizon, cfg.event_share, events=self.transition_events)
        return SequenceSampler(cfg.horizon)

    def transition_events(self, storage: Any) -> torch.Tensor:
        """bool ``[len(storage)]``: the stored play transitions that are events, here the
        ones changing more cells than an ordinary step (a subclass may find them another
        way). Called when windows are first drawn, after the subclass is built."""
        return event_transitions(changed_pixels(storage))

    @property
    def eval_event_windows(self) -> TensorDictBase | None:
        """Held-out windows holding an event (``event_share > 0`` only; ``None`` if none),
        found on first use by :meth:`transition_events`."""
        if self._eval_event_windows is False:
            windows = None
            if self.config.event_share > 0:
                generator = torch.Generator().manual_seed(self.config.seed)
                windows = event_windows(
                    self._eval_buffer,
                    self.config.horizon,
                    self.config.eval_sequences,
                    generator,
                    events=self.transition_events,
                )
            self._eval_event_windows = windows
        return self._eval_event_windows

    # ------------------------------------------------------------------ schedules
    def open_loop_length_at(self, step: int) -> int:
        """1 at step 0, growing linearly to ``horizon`` at ``open_loop_ramp * num_steps``."""
        cfg = self.config
        ramp = cfg.open_loop_ramp * cfg.num_steps
        frac = 1.0 if ramp <= 0 else min(1.0, step / ramp)
        return max(1, min(cfg.horizon, 1 + int(frac * (cfg.horizon - 1) + 1e-9)))

    def lr_at(self, step: int) -> float:
        """Cosine decay from ``lr`` to ``lr_final`` over ``num_steps``."""
        cfg = self.config
        frac = min(1.0, step / cfg.num_steps)
        return cfg.lr_final + 0.5 * (cfg.lr - cfg.lr_final) * (1.0 + math.cos(math.pi * frac))

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        load_module_state(self.model, state["model"], self.checkpoint_path, "model")
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except (ValueError, KeyError) as err:
            raise ValueError(
                f"checkpoint {self.checkpoint_path}: its optimizer state does not fit ({err})."
            ) from err

    # ------------------------------------------------------------------ steps
    def training_batch(self) -> TensorDictBase:
        """A batch of ``batch_size`` training windows on the trainer's device."""
        return self.buffer.sample(self.config.batch_size).to(self.device)

    def train_step(self) -> dict[str, float]:
        """One gradient step on a batch of windows; returns the detached metrics."""
        self.loss.open_loop_length = self.open_loop_length_at(self.step)
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr_at(self.step)
        out = self.loss(self.training_batch())
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        parameters = list(self.model.parameters())
        grad_norm = self.check_gradients(total, parameters)
        torch.nn.utils.clip_grads_with_norm_(parameters, self.config.grad_clip, grad_norm)
        self.optimizer.step()
        self.check_weights(self.model)
        self.step += 1
        metrics = {k: float(v.detach()) for k, v in out.items()}
        metrics["grad_norm"] = float(grad_norm)
        metrics["lr"] = self.optimizer.param_groups[0]["lr"]
        return metrics

    @property
    def evaluate_every(self) -> int:
        return self.config.eval_every

    @property
    def evaluate_at_end(self) -> bool:
        return True


def event_windows(
    buffer: TensorDictReplayBuffer,
    horizon: int,
    max_windows: int,
    generator: torch.Generator | None = None,
    events: Callable[[Any], torch.Tensor] | None = None,
) -> TensorDictBase | None:
    """Up to ``max_windows`` distinct ``[N, horizon]`` windows of ``buffer`` holding an event.

    Events as in :class:`~dorp_rl.data.EventWindowSampler` (``events``: its function
    of the storage giving the event transitions; default: changed cells); a random
    subset (from ``generator``) when there are more. ``None`` when no window holds one. Used to
    measure how a world model predicts the rare events (the door opening) that uniform
    held-out windows hardly contain.
    """
    sampler = EventWindowSampler(horizon, 1.0, events=events)
    starts, has_event = sampler.window_events(buffer.storage)
    starts = starts[has_event]
    if len(starts) == 0:
        return None
    if len(starts) > max_windows:
        starts = starts[torch.randperm(len(starts), generator=generator)[:max_windows]]
    return buffer[starts.unsqueeze(-1) + torch.arange(horizon)]
