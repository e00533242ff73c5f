"""Builds the paper's environments by name, for configs and command lines."""

from __future__ import annotations

from typing import Any

from dorp_rl.envs.grid_base import GridWorldEnv
from dorp_rl.envs.key_rooms import KeyCorridorEnv, KeyWallEnv
from dorp_rl.envs.rearrangement import ObjectRearrangementEnv

ENV_NAMES = ("rearrangement", "key-wall", "key-corridor")
_CLASSES: dict[str, type[GridWorldEnv]] = {
    "rearrangement": ObjectRearrangementEnv,
    "key-wall": KeyWallEnv,
    "key-corridor": KeyCorridorEnv,
}


def env_class(name: str) -> type[GridWorldEnv]:
    """The class of the environment called ``name`` (one of :data:`ENV_NAMES`).

    Examples:
        >>> from dorp_rl.envs import ENV_NAMES, env_class
        >>> ENV_NAMES, env_class("key-corridor").__name__
        (('rearrangement', 'key-wall', 'key-corridor'), 'KeyCorridorEnv')
    """
    if name not in _CLASSES:
        raise ValueError(f"env must be one of {ENV_NAMES}, got {name!r}.")
    return _CLASSES[name]


def make_env(name: str, num_objects: int = 1, **kwargs: Any) -> GridWorldEnv:
    """The environment called ``name`` (one of :data:`ENV_NAMES`).

    Args:
        name: ``"rearrangement"``, ``"key-wall"`` or ``"key-corridor"``.
        num_objects: number of blocks (rearrangement only; ignored by key rooms).
        **kwargs: passed to the env class (``batch_size``, ``device``, ``seed``, ...).

    Examples:
        >>> from dorp_rl.envs import make_env
        >>> make_env("rearrangement", num_objects=2, batch_size=(4,)).batch_size
        torch.Size([4])
    """
    cls = env_class(name)
    if cls is ObjectRearrangementEnv:
        return cls(num_objects=num_objects, **kwargs)
    return cls(**kwargs)
