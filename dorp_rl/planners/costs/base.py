"""The base of the costs: the rollout they read, how a planner folds their per-step
costs (``step_aggregation``), and how lazy values reach them (:func:`run_cost_lazy`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase

from dorp_rl.envs.planning import ImaginedFrames

__all__ = [
    "ImaginedFrameCost",
    "STEP_AGGREGATIONS",
    "MissingRolloutKeyError",
    "RolloutCost",
    "check_step_aggregation",
    "materialize_lazy",
    "run_cost_lazy",
]


#: How a planner folds a candidate's per-step costs ``[H]`` into its score.
STEP_AGGREGATIONS = ("min", "sum", "final")


class MissingRolloutKeyError(KeyError, ValueError):
    """A key a cost needs is neither predicted by the planning env nor in the acting tensordict."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else ""


def get_rollout_key(rollout: TensorDictBase, key: NestedKey, cost_name: str) -> torch.Tensor:
    """``rollout.get(key)``, or a :class:`MissingRolloutKeyError` that names the key."""
    value = rollout.get(key, None)
    if value is None:
        available = sorted(str(k) for k in rollout.keys(True, True))
        hint = (
            "the planning env does not produce it"
            if isinstance(unravel_key(key), tuple) and unravel_key(key)[0] == "next"
            else "the tensordict given to the planner does not hold it"
        )
        raise MissingRolloutKeyError(
            f"{cost_name} needs the key {key!r}, which is missing from the imagined rollout "
            f"({hint}). Keys present: {available}."
        )
    return value


def check_step_aggregation(step_aggregation: str) -> str:
    """``step_aggregation`` if it is one of :data:`STEP_AGGREGATIONS`, else a ``ValueError``."""
    if step_aggregation not in STEP_AGGREGATIONS:
        raise ValueError(
            f"step_aggregation (how a candidate's per-step costs fold into its score) must be "
            f"one of {STEP_AGGREGATIONS}, got {step_aggregation!r}."
        )
    return step_aggregation


def compact_broadcast(tensor: torch.Tensor, keep_last: int) -> torch.Tensor:
    """Narrows every broadcast (stride-0) leading dimension to size 1.

    Root keys of a rollout are expanded views; converting one to float would otherwise
    materialise it ``N * H`` times. The result still broadcasts against the full shape.
    """
    for dim in range(tensor.dim() - keep_last):
        if tensor.stride(dim) == 0 and tensor.shape[dim] > 1:
            tensor = tensor.narrow(dim, 0, 1)
    return tensor


def materialize_lazy(
    rollout: TensorDictBase,
    lazy: Mapping[NestedKey, Any],
    keys: Sequence[NestedKey] | None = None,
) -> TensorDictBase:
    """Writes the ``lazy`` values (those of ``keys``; ``None``: all) into ``rollout``.

    Values the rollout already holds are left as they are; a lazy value is a tensor or a
    :class:`~dorp_rl.envs.planning.LazyValue` (its ``materialize()`` gives the tensor).
    Returns ``rollout``.
    """
    wanted = None if keys is None else {unravel_key(k) for k in keys}
    for key, value in lazy.items():
        key = unravel_key(key)
        if (wanted is not None and key not in wanted) or key in rollout.keys(True, True):
            continue
        rollout.set(key, value if isinstance(value, torch.Tensor) else value.materialize())
    return rollout


def lazy_frames(
    rollout: TensorDictBase, lazy: Mapping[NestedKey, Any], key: NestedKey
) -> ImaginedFrames | None:
    """``lazy[key]`` if it is :class:`~dorp_rl.envs.planning.ImaginedFrames` the rollout does
    not hold drawn (a cost may then read the states behind them), else ``None``."""
    frames = lazy.get(key)
    if not isinstance(frames, ImaginedFrames) or key in rollout.keys(True, True):
        return None
    return frames


def run_cost_lazy(
    cost: Callable, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
) -> TensorDictBase:
    """Runs ``cost`` on ``rollout`` whose ``lazy`` values are not materialised yet.

    A cost whose class declares ``forward_lazy(rollout, lazy)`` (:class:`RolloutCost`,
    :class:`CostSequence`) is handed the lazy values; any other module gets those it
    reads (its ``in_keys``; all of them when it declares none) materialised into the
    rollout and is called as usual. Without lazy values it is simply ``cost(rollout)``.
    Returns the rollout with the cost's outputs.
    """
    if not lazy:
        out = cost(rollout)
    elif callable(getattr(type(cost), "forward_lazy", None)):
        out = cost.forward_lazy(rollout, lazy)
    else:
        materialize_lazy(rollout, lazy, getattr(cost, "in_keys", None) or None)
        out = cost(rollout)
    return rollout if out is None else out


class RolloutCost(TensorDictModuleBase):
    """Base class of the costs: writes a per-step cost float ``[*B, N, H]`` under ``out_key``.

    Subclasses set ``in_keys`` (the keys they read) and implement
    :meth:`per_step_cost`; :meth:`forward` writes its result into the rollout and
    returns the rollout, as TensorDict modules do. Planners whose env leaves values
    lazy call :meth:`forward_lazy` (through :meth:`per_step_cost_lazy`), which by
    default materialises them; a subclass that redefines :meth:`per_step_cost` or
    :meth:`forward` without :meth:`per_step_cost_lazy` / :meth:`forward_lazy` gets that
    default back (``__init_subclass__``), so its own method is what runs.

    Args:
        out_key: where the per-step cost is written (``out_keys == [out_key]``).
        step_aggregation: how planners fold a candidate's per-step costs into its score
            (``"min"``, ``"sum"`` or ``"final"``, see the module docstring).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import RolloutCost
        >>> class StepsTaken(RolloutCost):
        ...     def __init__(self):
        ...         super().__init__(out_key="steps", step_aggregation="final")
        ...         self.in_keys = ["action"]
        ...
        ...     def per_step_cost(self, rollout):
        ...         return torch.arange(1.0, rollout.shape[-1] + 1).expand(rollout.shape)
        >>> actions = torch.zeros(2, 5, 3, 1, dtype=torch.int64)
        >>> rollout = TensorDict(action=actions, batch_size=(2, 5, 3))
        >>> StepsTaken()(rollout)["steps"][0, 0]
        tensor([1., 2., 3.])
    """

    def __init__(self, *, out_key: NestedKey = "cost", step_aggregation: str = "sum") -> None:
        super().__init__()
        self.out_key = unravel_key(out_key)
        self.in_keys = []
        self.out_keys = [self.out_key]
        self.step_aggregation = check_step_aggregation(step_aggregation)
        #: root keys the cost reads as frames (a goal image, the start frame): planners
        #: check them against the planning env once per call and hand them over as uint8
        self.root_frame_keys: list[NestedKey] = []

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        """The per-step cost, float ``[*B, N, H]``, of a rollout ``[*B, N, H]``."""
        raise NotImplementedError

    def forward(self, rollout: TensorDictBase) -> TensorDictBase:
        rollout.set(self.out_key, self.per_step_cost(rollout))
        return rollout

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        """:meth:`per_step_cost` of ``rollout`` completed by the ``lazy`` values.

        ``lazy`` maps rollout keys the planning env left out of ``rollout`` (e.g.
        ``("next", "pixels")``) to values computed on demand
        (:class:`~dorp_rl.envs.planning.LazyValue`, such as
        :class:`~dorp_rl.envs.planning.ImaginedFrames`). This default materialises the
        ones among :attr:`in_keys` into the rollout and calls :meth:`per_step_cost`; a
        cost that can read a lazy value for less (distinct frames only, distances from
        the states) overrides it, with exactly the same result.
        """
        materialize_lazy(rollout, lazy, self.in_keys)
        return self.per_step_cost(rollout)

    def forward_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> TensorDictBase:
        """:meth:`forward` through :meth:`per_step_cost_lazy`: what ``forward`` writes on
        the rollout with its lazy values materialised (see :func:`run_cost_lazy`)."""
        rollout.set(self.out_key, self.per_step_cost_lazy(rollout, lazy))
        return rollout

    def __init_subclass__(cls, **kwargs) -> None:
        # The contract: a class's lazy methods compute what its own per_step_cost /
        # forward compute. A subclass that redefines one of those without redefining its
        # lazy counterpart gets the default that materialises the lazy values and calls
        # the redefined method, so that its override is what runs.
        super().__init_subclass__(**kwargs)
        own = vars(cls)
        if "per_step_cost" in own and "per_step_cost_lazy" not in own:
            cls.per_step_cost_lazy = RolloutCost.per_step_cost_lazy
        if "forward" in own and "forward_lazy" not in own:
            cls.forward_lazy = _forward_materialized

    def extra_repr(self) -> str:
        return f"out_key={self.out_key!r}, step_aggregation={self.step_aggregation!r}"


class ImaginedFrameCost(RolloutCost):
    """A cost of the imagined frames under ``pixels_key`` that reads them for less when
    they come as lazy :class:`~dorp_rl.envs.planning.ImaginedFrames`.

    Subclasses set ``pixels_key`` and implement ``_per_step_cost(rollout, imagined)``:
    ``imagined`` is the lazy frames, or ``None`` when the rollout holds the frames; both
    must give the same costs. Lazy values of other kinds are materialised first.
    """

    pixels_key: NestedKey

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        return self._per_step_cost(rollout, None)

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        frames = lazy_frames(rollout, lazy, self.pixels_key)
        if frames is None:
            return super().per_step_cost_lazy(rollout, lazy)
        return self._per_step_cost(rollout, frames)

    def _per_step_cost(
        self, rollout: TensorDictBase, imagined: ImaginedFrames | None
    ) -> torch.Tensor:
        raise NotImplementedError


def _forward_materialized(
    self: RolloutCost, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
) -> TensorDictBase:
    """``forward_lazy`` of a cost that redefines ``forward``: materialise, then call it."""
    materialize_lazy(rollout, lazy, self.in_keys or None)
    out = self(rollout)
    return rollout if out is None else out
