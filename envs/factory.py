"""Builds an environment by the name of its profile, for configs and command lines."""

from __future__ import annotations

from typing import Any

from torchrl.envs import EnvBase

from dorp_rl.envs import key_rooms, rearrangement  # noqa: F401  (they register their profiles)
from dorp_rl.envs.profile import env_profile

#: The project's own env profiles (registered by their modules).
ENV_NAMES = ("rearrangement", "key-wall", "key-corridor")


def env_class(name: str) -> type:
    """The class of the environment whose profile is ``name`` (one with an ``env_type``).

    Examples:
        >>> from dorp_rl.envs import ENV_NAMES, env_class
        >>> ENV_NAMES, env_class("key-corridor").__name__
        (('rearrangement', 'key-wall', 'key-corridor'), 'KeyCorridorEnv')
    """
    profile = env_profile(name)
    if profile.env_type is None:
        raise ValueError(f"env profile {name!r} declares no env_type.")
    return profile.env_type


def make_env(name: str, num_objects: int | None = None, **kwargs: Any) -> EnvBase:
    """The environment of profile ``name`` (a registered name or an import path).

    Args:
        name: ``"rearrangement"``, ``"key-wall"``, ``"key-corridor"``, another registered
            profile or ``"package.module:attribute"`` (:func:`~dorp_rl.envs.env_profile`).
        num_objects: number of objects of an env that counts them (None: the profile's
            default; an env that does not count objects takes only 1 or None).
        **kwargs: passed to the profile's factory (``batch_size``, ``device``, ``seed``, ...).

    Examples:
        >>> from dorp_rl.envs import make_env
        >>> make_env("rearrangement", num_objects=2, batch_size=(4,)).batch_size
        torch.Size([4])
    """
    profile = env_profile(name)
    if not profile.counts_objects and num_objects == 1:
        num_objects = None
    return profile.build(num_objects, **kwargs)
