"""What the generic parts read off any TorchRL env: its discrete actions and its identity.

Nothing here asks which env it has: an env is described by its specs (and by a
``config()`` method when it declares one), so a user's env, a gymnasium env through
torchrl's ``GymEnv`` and the project's own envs are read the same way.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torchrl.data import Categorical, OneHot

__all__ = ["DiscreteActions", "env_device", "env_identity", "qualified_name"]


@dataclass(frozen=True)
class DiscreteActions:
    """The discrete action space of a TorchRL env: ``Categorical`` or ``OneHot``.

    Attributes:
        key: the env's action key.
        num_actions: how many actions there are.
        one_hot: whether an action is a one-hot vector (else an integer index).
        shape: the shape of one env's action (``(1,)`` or ``()`` for an index,
            ``(num_actions,)`` for a one-hot).
        dtype: the action's dtype.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.envs.spec import DiscreteActions
        >>> actions = DiscreteActions.of(KeyWallEnv(batch_size=(2,)))
        >>> actions.num_actions, actions.one_hot, actions.shape
        (4, False, (1,))
        >>> actions.sample((2,), torch.Generator().manual_seed(0)).shape
        torch.Size([2, 1])
    """

    key: Any
    num_actions: int
    one_hot: bool
    shape: tuple[int, ...]
    dtype: torch.dtype

    @classmethod
    def of(cls, env: Any) -> DiscreteActions:
        """Reads the action spec of ``env`` (one action key).

        Raises:
            ValueError: an env that is not a TorchRL env, has several action keys, or
                whose action is not discrete (``Categorical`` or ``OneHot``).
        """
        full = getattr(env, "full_action_spec", None)
        if full is None:
            raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
        keys = list(full.keys(True, True))
        if len(keys) != 1:
            raise ValueError(
                f"{type(env).__name__} must have one action key, it has {keys}: DORP plans "
                "over one discrete action per step."
            )
        key = keys[0]
        spec = full[key]
        batch = len(getattr(env, "batch_size", ()))
        shape = tuple(spec.shape[batch:])
        if isinstance(spec, OneHot):
            return cls(key, int(spec.space.n), True, shape, spec.dtype)
        if isinstance(spec, Categorical) and shape in ((), (1,)):
            return cls(key, int(spec.space.n), False, shape, spec.dtype)
        raise ValueError(
            f"{type(env).__name__}'s action {key!r} must be discrete: a Categorical of one "
            f"index or a OneHot, got {type(spec).__name__} of shape {list(shape)}. "
            "Continuous or multi-discrete actions are not planned over."
        )

    def sample(
        self,
        batch_shape: tuple[int, ...] | torch.Size,
        generator: torch.Generator,
        device: torch.device | str = "cpu",
    ) -> torch.Tensor:
        """Uniform random actions ``[*batch_shape, *shape]`` drawn from ``generator``."""
        batch_shape = tuple(batch_shape)
        index = torch.randint(
            self.num_actions, batch_shape, generator=generator, device=generator.device
        ).to(device)
        if self.one_hot:
            return torch.nn.functional.one_hot(index, self.num_actions).to(self.dtype)
        return index.reshape(*batch_shape, *self.shape).to(self.dtype)

    def from_index(self, index: torch.Tensor) -> torch.Tensor:
        """Int indices ``[*B, 1]`` as actions in this layout (``[*B, *shape]``)."""
        index = index.to(torch.int64).reshape(*index.shape[:-1])
        if self.one_hot:
            return torch.nn.functional.one_hot(index, self.num_actions).to(self.dtype)
        return index.reshape(*index.shape, *self.shape).to(self.dtype)

    def index(self, action: torch.Tensor) -> torch.Tensor:
        """Actions in this layout as int64 indices ``[*B, 1]``."""
        if self.one_hot:
            return action.to(torch.int64).argmax(-1, keepdim=True)
        if self.shape == ():
            return action.unsqueeze(-1).to(torch.int64)
        return action.to(torch.int64)


def env_device(env: Any) -> torch.device:
    """The device of ``env`` (the CPU for an env made without one)."""
    device = getattr(env, "device", None)
    return torch.device("cpu") if device is None else torch.device(device)


def env_identity(env: Any) -> dict:
    """What makes data, codes and graphs of ``env`` belong to it, as a JSON-able dict.

    An env that declares ``config()`` (the project's envs do) is identified by it; any
    other by its class and the shapes and dtypes of its observation and action specs.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.envs.spec import env_identity
        >>> env_identity(KeyWallEnv(batch_size=(2,)))["env"]
        'KeyWallEnv'
    """
    # Looked up on the class: batched envs (SerialEnv, ParallelEnv) forward unknown
    # attributes to their sub-envs, which may not exist yet.
    if callable(getattr(type(env), "config", None)):
        return env.config()
    batch = len(getattr(env, "batch_size", ()))

    def describe(spec: Any) -> dict:
        return {
            "/".join(k) if isinstance(k, tuple) else str(k): {
                "shape": list(spec[k].shape[batch:]),
                "dtype": str(spec[k].dtype).removeprefix("torch."),
            }
            for k in spec.keys(True, True)
        }

    actions = DiscreteActions.of(env)
    return {
        "env": qualified_name(type(env)),
        "observation": describe(env.full_observation_spec),
        "actions": {"num_actions": actions.num_actions, "one_hot": actions.one_hot},
    }


def qualified_name(obj: Any) -> str:
    """``module.qualname`` of a class or function, the same whether its module runs as a
    script or is imported.

    A script's definitions live in ``__main__``; that is replaced by the name the module
    is imported under (``python -m pkg.mod``: ``pkg.mod``; ``python path/mod.py``:
    ``mod``), so a checkpoint written by ``python examples/own_environment.py`` fits the
    same env imported as ``own_environment`` (``--env own_environment:PROFILE``).

    Examples:
        >>> from dorp_rl.envs.spec import qualified_name
        >>> from dorp_rl.envs import KeyWallEnv
        >>> qualified_name(KeyWallEnv)
        'dorp_rl.envs.key_rooms.KeyWallEnv'
    """
    module = getattr(obj, "__module__", None) or ""
    if module == "__main__":
        main = sys.modules.get("__main__")
        spec = getattr(main, "__spec__", None)
        if spec is not None and spec.name and spec.name != "__main__":
            module = spec.name
        elif getattr(main, "__file__", None):
            module = Path(main.__file__).stem
    return f"{module}.{getattr(obj, '__qualname__', repr(obj))}"
