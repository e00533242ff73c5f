"""The low level a policy imagines with: one name for the true dynamics, one factory.

``make_planning_env(env, low_level)`` is what the DORP policy factory, the evaluation and
the ``dorp`` command call to turn a ``low_level`` argument into a planning env.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn
from torchrl.envs import EnvBase

from dorp_rl.envs.latent_planning import LatentModelEnv
from dorp_rl.envs.planning import StatelessEnvModel, VideoModelEnv
from dorp_rl.envs.spec import DiscreteActions

__all__ = ["TRUE_DYNAMICS", "make_planning_env"]

#: The one name of the env's own dynamics as the low level.
TRUE_DYNAMICS = "gt"


def make_planning_env(env: EnvBase, low_level: str | Path | EnvBase | nn.Module) -> EnvBase:
    """The planning env of ``low_level`` for ``env``'s tasks.

    Args:
        env: the acting env (its true dynamics, and the env a checkpoint must fit).
        low_level: ``"gt"`` (:data:`TRUE_DYNAMICS`: ``env``'s own dynamics: what its
            ``true_dynamics()`` returns when it declares one, as the grid worlds do
            (:class:`~dorp_rl.envs.GroundTruthModelEnv`); else the env itself when it
            steps any leading shape (``batch_size=()``, not batch-locked); else
            :class:`~dorp_rl.envs.planning.StatelessEnvModel` over it), a planning env (used as it is),
            a latent world model (:class:`~dorp_rl.modules.LatentWorldModel`, driven by
            :class:`~dorp_rl.envs.LatentModelEnv`), a model with ``predict(pixels,
            action)`` (wrapped in :class:`~dorp_rl.envs.VideoModelEnv`) or the path of a
            checkpoint of either (loaded against ``env``).

    Raises:
        ValueError: any other value, naming what is accepted.

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.policies import make_planning_env
        >>> type(make_planning_env(ObjectRearrangementEnv(num_objects=1), "gt")).__name__
        'GroundTruthModelEnv'
    """
    if isinstance(low_level, EnvBase):
        return low_level
    if isinstance(low_level, str) and low_level == TRUE_DYNAMICS:
        declared = getattr(env, "true_dynamics", None)
        if callable(declared):
            return declared()
        if env.batch_size == () and not env.batch_locked:
            return env
        return StatelessEnvModel(env)
    if isinstance(low_level, str) and low_level in ("ground_truth", "ground-truth"):
        raise ValueError(
            f"low_level {low_level!r}: the true dynamics are spelled {TRUE_DYNAMICS!r}."
        )
    if isinstance(low_level, (str, Path)):  # a checkpoint; a missing one is named there
        from dorp_rl.trainers import load_world_model

        low_level = load_world_model(low_level, env)
    if callable(getattr(low_level, "as_world_model", None)):
        # A latent world model: frames decoded at every step, for costs that read pixels.
        return LatentModelEnv(low_level, decode=True)
    if callable(getattr(low_level, "predict", None)):
        return VideoModelEnv(low_level, DiscreteActions.of(env).num_actions)
    raise ValueError(
        f"low_level must be {TRUE_DYNAMICS!r} (the true dynamics), a planning env, a latent "
        "world model, a model with predict(pixels, action) or the path of a world-model "
        "checkpoint, got "
        f"{type(low_level).__name__}."
    )
