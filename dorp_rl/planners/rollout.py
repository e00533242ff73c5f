"""The rollout of candidate plans that a planner scores: one object for every planning env.

A planner imagines ``N`` candidate action sequences of ``H`` steps from each of ``b``
acting rows; :class:`CandidateRollout` is what comes back, whether the planning env was
stepped or imagined the candidates in bulk (``imagine_candidates``, which may leave
values such as the frames lazy). Costs read it through one interface:

- :meth:`CandidateRollout.get` gives any key's tensor (a lazy value is computed the first
  time it is asked for, then kept);
- :meth:`CandidateRollout.frames` gives a key's frames as
  :class:`~dorp_rl.envs.planning.HeldFrames` or
  :class:`~dorp_rl.envs.planning.ImaginedFrames`, one interface that owns deduplication
  (:meth:`distinct`, by the one frame hash :func:`~dorp_rl.envs.planning.row_hashes`)
  and exact distances to goal images where the env can give them without drawing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key

from dorp_rl.envs.planning import HeldFrames, ImaginedFrames

__all__ = ["CandidateRollout"]


class CandidateRollout:
    """Candidates' rollout ``[*B, N, H]``: a tensordict and the values left lazy in it.

    Args:
        td: the rollout tensordict: ``action``, the ``("next", ...)`` values computed,
            the acting rows' root keys broadcast over candidates and steps.
        lazy: rollout keys the planning env left out of ``td`` -> values computed on
            demand (objects with ``materialize()``, such as
            :class:`~dorp_rl.envs.planning.ImaginedFrames`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import CandidateRollout
        >>> frames = torch.zeros(2, 5, 4, 3, 8, 8, dtype=torch.uint8)
        >>> rollout = CandidateRollout(TensorDict({("next", "pixels"): frames}, batch_size=(2, 5, 4)))
        >>> distinct, _, inverse, _ = rollout.frames(("next", "pixels")).distinct()
        >>> distinct.shape[0], inverse.shape[0]
        (1, 40)
    """

    def __init__(self, td: TensorDictBase, lazy: Mapping[NestedKey, Any] | None = None) -> None:
        if not isinstance(td, TensorDictBase):
            raise ValueError(f"a rollout is a TensorDict [*B, N, H], got {type(td).__name__}.")
        self.td = td
        self.lazy = {unravel_key(k): v for k, v in (lazy or {}).items()}

    @classmethod
    def of(cls, rollout: TensorDictBase | CandidateRollout) -> CandidateRollout:
        """``rollout`` itself, or a tensordict as a rollout with nothing lazy."""
        return rollout if isinstance(rollout, CandidateRollout) else cls(rollout)

    @property
    def batch_size(self) -> torch.Size:
        return self.td.batch_size

    shape = batch_size

    @property
    def batch_dims(self) -> int:
        return self.td.batch_dims

    @property
    def device(self) -> torch.device | None:
        return self.td.device

    def keys(self) -> frozenset[NestedKey]:
        """Every key of the rollout, computed or lazy (leaves, nested keys as tuples)."""
        return frozenset(self.td.keys(True, True)) | frozenset(self.lazy)

    def __contains__(self, key: NestedKey) -> bool:
        return unravel_key(key) in self.keys()

    def get(self, key: NestedKey, default: Any = None) -> Any:
        """The tensor under ``key`` (a lazy value is computed now and kept), else ``default``."""
        key = unravel_key(key)
        value = self.td.get(key, None)
        if value is not None:
            return value
        lazy = self.lazy.pop(key, None)
        if lazy is None:
            return default
        value = lazy if isinstance(lazy, torch.Tensor) else lazy.materialize()
        self.td.set(key, value)
        return value

    def __getitem__(self, key: NestedKey) -> torch.Tensor:
        value = self.get(key)
        if value is None:
            raise KeyError(f"the rollout has no {key!r}; it holds {sorted(map(str, self.keys()))}.")
        return value

    def lazy_value(self, key: NestedKey) -> Any:
        """The object still lazy under ``key`` (a cost that knows its kind may read it for
        less), or ``None`` once it is computed or if there is none."""
        return self.lazy.get(unravel_key(key))

    def set(self, key: NestedKey, value: torch.Tensor) -> CandidateRollout:
        """Writes ``value`` (a cost's per-step output) under ``key``."""
        self.lazy.pop(unravel_key(key), None)
        self.td.set(key, value)
        return self

    def frames(self, key: NestedKey) -> HeldFrames | ImaginedFrames | None:
        """The frames under ``key`` (lazy imagined frames stay undrawn); ``None`` if absent."""
        key = unravel_key(key)
        lazy = self.lazy.get(key)
        if isinstance(lazy, ImaginedFrames):
            return lazy
        value = self.get(key)
        return None if value is None else HeldFrames(value)

    def materialized(self, keys: Sequence[NestedKey] | None = None) -> TensorDictBase:
        """The tensordict with the lazy values of ``keys`` (``None``: all) computed."""
        wanted = list(self.lazy) if keys is None else [unravel_key(k) for k in keys]
        for key in wanted:
            if key in self.lazy:
                self.get(key)
        return self.td

    def __repr__(self) -> str:
        return f"CandidateRollout(batch_size={list(self.batch_size)}, lazy={sorted(map(str, self.lazy))})"
