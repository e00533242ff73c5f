"""Native gymnasium versions of the pixel environments, running the same torch dynamics."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from dorp_rl.envs.grid_base import GRID_SIZE, GridWorldEnv
from dorp_rl.envs.key_rooms import KeyCorridorEnv, KeyWallEnv
from dorp_rl.envs.rearrangement import ObjectRearrangementEnv
from dorp_rl.frames import frames_to_rgb_array
from dorp_rl.validation import check_int, check_seed

ENV_CLASSES: dict[str, type[GridWorldEnv]] = {
    "ObjectRearrangement": ObjectRearrangementEnv,
    "KeyWall": KeyWallEnv,
    "KeyCorridor": KeyCorridorEnv,
}


class GymnasiumGridEnv(gymnasium.Env):
    """A single copy of a :class:`~dorp_rl.envs.GridWorldEnv` behind gymnasium's API.

    Observations are a ``Dict`` of ``pixels`` and ``goal_pixels``, uint8 ``(16, 16, 3)``
    (channel-last, as gymnasium expects); ``info`` carries ``state``, ``goal_state``,
    ``success`` and ``lower_bound_steps``. ``reset(options={"state": ..., "goal_state": ...})``
    starts from given configurations. Truncation comes from the torch env's step limit.

    Args:
        env_name: ``"ObjectRearrangement"``, ``"KeyWall"`` or ``"KeyCorridor"``.
        render_mode: ``None`` or ``"rgb_array"`` (frames upscaled by ``render_scale``).
        render_scale: pixel size of one grid cell in rendered frames.
        **env_kwargs: forwarded to the torch env (``num_objects``, ``max_steps``, ...).

    Examples:
        >>> import gymnasium, dorp_rl.envs
        >>> env = gymnasium.make("dorp_rl/ObjectRearrangement-v0", num_objects=2)
        >>> obs, info = env.reset(seed=0)
        >>> obs["pixels"].shape, info["state"].shape
        ((16, 16, 3), (2, 2))
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 8}

    def __init__(
        self,
        env_name: str,
        render_mode: str | None = None,
        render_scale: int = 8,
        **env_kwargs: Any,
    ) -> None:
        if env_name not in ENV_CLASSES:
            raise ValueError(f"env_name must be one of {sorted(ENV_CLASSES)}, got {env_name!r}.")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}.")
        for name in ("batch_size", "batch_locked"):
            if name in env_kwargs:
                raise ValueError(
                    f"{name}={env_kwargs[name]!r}: a gymnasium env is one env (batch_size=()); "
                    "for a batch use gymnasium.vector or the torch env "
                    f"dorp_rl.envs.{ENV_CLASSES[env_name].__name__}(batch_size=...)."
                )
        self.env = ENV_CLASSES[env_name](batch_size=(), **env_kwargs)
        self.render_mode = render_mode
        self.render_scale = check_int("render_scale", render_scale, low=1)
        image = spaces.Box(0, 255, (GRID_SIZE, GRID_SIZE, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict({"pixels": image, "goal_pixels": image})
        self.action_space = spaces.Discrete(self.env.num_actions)
        self._td: TensorDict | None = None

    def _observe(self, td: TensorDict) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        obs = {
            key: td.get(key).permute(1, 2, 0).cpu().numpy().copy()
            for key in ("pixels", "goal_pixels")
        }
        state, goal = td.get("state"), td.get("goal_state")
        info = {
            "state": state.cpu().numpy().copy(),
            "goal_state": goal.cpu().numpy().copy(),
            "success": bool(td.get("success").item()),
            "lower_bound_steps": int(self.env.lower_bound_steps(state, goal)),
        }
        return obs, info

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        seed = check_seed(seed, optional=True)
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        given = {}
        for key in ("state", "goal_state"):
            if options and options.get(key) is not None:
                value = np.asarray(options[key])
                if value.dtype.kind not in "iu":
                    raise ValueError(
                        f"options[{key!r}] must hold integers, got dtype {value.dtype}."
                    )
                given[key] = torch.as_tensor(value, dtype=torch.int64)
        unknown = set(options or {}) - {"state", "goal_state"}
        if unknown:
            raise ValueError(
                f"unknown reset options {sorted(unknown)}; expected 'state', 'goal_state'."
            )
        td = self.env.reset(TensorDict(given, batch_size=()), set_state=True)
        self._td = td
        return self._observe(td)

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self._td is None:
            raise RuntimeError("call reset() before step().")
        if not self.action_space.contains(action) and not (
            np.ndim(action) == 0 and np.asarray(action).dtype.kind in "iu"
        ):
            raise ValueError(
                f"action must be an integer in [0, {self.env.num_actions - 1}], got {action!r}."
            )
        self._td.set("action", torch.tensor([int(action)], dtype=torch.int64))
        out = self.env.step(self._td)["next"]
        self._td = out
        obs, info = self._observe(out)
        return (
            obs,
            float(out.get("reward").item()),
            bool(out.get("terminated").item()),
            bool(out.get("truncated").item()),
            info,
        )

    def render(self) -> np.ndarray | None:
        if self.render_mode is None or self._td is None:
            return None
        return frames_to_rgb_array(self._td.get("pixels"), self.render_scale)


def register_gymnasium_envs() -> None:
    """Registers ``dorp_rl/ObjectRearrangement-v0``, ``dorp_rl/KeyWall-v0`` and ``dorp_rl/KeyCorridor-v0``."""
    for name in ENV_CLASSES:
        env_id = f"dorp_rl/{name}-v0"
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="dorp_rl.envs.gymnasium_envs:GymnasiumGridEnv",
            kwargs={"env_name": name},
        )
