"""What the planning envs share: a stateless TorchRL env over any leading batch shape
(:class:`PlanningEnvBase`), the check of a planned action, and the protocols of lazy
values and frame predictors.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.envs.grid_base import (
    GRID_SIZE,
    CheckedRolloutLength,
)
from dorp_rl.validation import (
    check_action,
    check_device,
    check_int,
)

__all__ = [
    "FramePredictor",
    "LazyValue",
    "PlanningEnvBase",
    "PlanningEnvSpecs",
    "check_planning_action",
]


_FRAME = (3, GRID_SIZE, GRID_SIZE)


_FRAME_BYTES = 3 * GRID_SIZE * GRID_SIZE


@runtime_checkable
class LazyValue(Protocol):
    """A rollout value computed only when asked for (``imagine_candidates``' ``lazy``)."""

    def materialize(self) -> torch.Tensor:
        """The value as the tensor stepping the env would have written, ``[b, N, H, ...]``."""
        ...


@runtime_checkable
class FramePredictor(Protocol):
    """What :class:`VideoModelEnv` needs from a video prediction model."""

    def predict(
        self, pixels: torch.Tensor, action: torch.Tensor, deterministic: bool = True
    ) -> torch.Tensor:
        """Next frames: uint8 ``[N, 3, 16, 16]`` and int64 ``[N, 1]`` -> uint8 ``[N, 3, 16, 16]``."""
        ...


def check_planning_action(
    action: torch.Tensor, num_actions: int, batch_shape: torch.Size | None = None
) -> torch.Tensor:
    """Validates an action tensor int ``[*B, 1]`` in ``[0, num_actions)``; returns int64 ``[*B, 1]``.

    ``batch_shape``, if given, is the expected ``B`` (see :func:`dorp_rl.validation.check_action`).
    """
    shape = None if batch_shape is None else (*batch_shape, 1)
    return check_action(action, num_actions, shape=shape)


class PlanningEnvSpecs:
    """The specs and outputs the planning envs share (a mixin): ``pixels`` and
    ``goal_pixels`` frames, a one-of-``num_actions`` action, a zero reward and done flags
    that stay ``False`` (imagined rollouts run for the whole horizon)."""

    _supports_set_state = True

    def _declare_planning_specs(self, num_actions: int) -> None:
        self.num_actions = num_actions
        image = Bounded(low=0, high=255, shape=_FRAME, dtype=torch.uint8, device=self.device)
        self.observation_spec = Composite(
            pixels=image, goal_pixels=image.clone(), **self._extra_observation_specs()
        )
        self.action_spec = Categorical(num_actions, shape=(1,), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())

    def _extra_observation_specs(self) -> dict:
        return {}

    def _outputs(
        self,
        shape: torch.Size,
        pixels: torch.Tensor,
        goal_pixels: torch.Tensor | None,
        *,
        reward: bool,
        **extra,
    ) -> TensorDict:
        """The output tensordict: frames, extras, all-``False`` done flags, a zero reward on steps."""
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        out = TensorDict(
            pixels=pixels,
            done=false,
            terminated=false.clone(),
            truncated=false.clone(),
            **extra,
            batch_size=shape,
            device=self.device,
        )
        if reward:
            out.set("reward", torch.zeros((*shape, 1), dtype=torch.float32, device=self.device))
        if goal_pixels is not None:
            out.set("goal_pixels", goal_pixels)
        return out


class PlanningEnvBase(PlanningEnvSpecs, CheckedRolloutLength, EnvBase):
    """A stateless planning env over any leading shape (``batch_size=()``) with the shared
    specs (:class:`PlanningEnvSpecs`)."""

    def __init__(self, num_actions: int, device: torch.device | str | None) -> None:
        num_actions = check_int("num_actions", num_actions, low=1)
        device = check_device(device, optional=True)
        super().__init__(device=torch.device("cpu") if device is None else device, batch_size=())
        self.__dict__["_batch_locked"] = False
        self._declare_planning_specs(num_actions)
