"""The base of the costs: the rollout they read (a
:class:`~dorp_rl.planners.CandidateRollout`), how a planner folds their per-step costs
(``step_aggregation``), and how a planner runs any cost module on a rollout
(:func:`score_rollout`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase

from dorp_rl.envs.planning import RolloutFrames
from dorp_rl.planners.rollout import CandidateRollout

__all__ = [
    "STEP_AGGREGATIONS",
    "MissingRolloutKeyError",
    "RolloutCost",
    "check_step_aggregation",
    "score_rollout",
]


#: How a planner folds a candidate's per-step costs ``[H]`` into its score.
STEP_AGGREGATIONS = ("min", "sum", "final")


class MissingRolloutKeyError(KeyError, ValueError):
    """A key a cost needs is neither predicted by the planning env nor in the acting tensordict."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else ""


def get_rollout_key(rollout: CandidateRollout, key: NestedKey, cost_name: str) -> torch.Tensor:
    """``rollout.get(key)``, or a :class:`MissingRolloutKeyError` that names the key."""
    value = rollout.get(key, None)
    if value is None:
        available = sorted(str(k) for k in rollout.keys())
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


def get_rollout_frames(
    rollout: CandidateRollout | TensorDictBase, key: NestedKey, cost_name: str
) -> RolloutFrames:
    """``rollout.frames(key)`` (held or imagined frames; a plain tensordict's are held), or
    a :class:`MissingRolloutKeyError`."""
    frames = CandidateRollout.of(rollout).frames(key)
    if frames is None:
        get_rollout_key(rollout, key, cost_name)  # raises, naming the key
    return frames


def score_rollout(cost: Callable, rollout: CandidateRollout) -> TensorDictBase:
    """Runs ``cost`` on the candidates' ``rollout``; returns the rollout tensordict with the
    cost's outputs.

    A :class:`RolloutCost` (and a :class:`~dorp_rl.planners.CostSequence`) reads the
    rollout itself, lazy values included; any other module (a ``TensorDictModule``, a
    ``TensorDictSequential``, a cost class that redefines ``forward``) is called on the
    tensordict with the values it reads (its ``in_keys``; all when it declares none)
    computed.
    """
    if callable(getattr(cost, "score", None)):
        return cost.score(rollout)
    td = rollout.materialized(getattr(cost, "in_keys", None) or None)
    out = cost(td)
    return td if out is None else out


class RolloutCost(TensorDictModuleBase):
    """Base class of the costs: writes a per-step cost float ``[*B, N, H]`` under ``out_key``.

    Subclasses set ``in_keys`` (the keys they read) and implement :meth:`per_step_cost`
    of a :class:`~dorp_rl.planners.CandidateRollout` (``rollout.get(key)`` for tensors,
    ``rollout.frames(key)`` for frames that may be imagined and drawn only when needed):
    one implementation, whatever the planning env. Called on a tensordict, as TensorDict
    modules are, the cost writes its result into it and returns it.

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

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        """The per-step cost, float ``[*B, N, H]``, of a rollout ``[*B, N, H]``."""
        raise NotImplementedError

    def score(self, rollout: CandidateRollout) -> TensorDictBase:
        """Writes :meth:`per_step_cost` into ``rollout``; returns its tensordict. (A
        subclass that redefines ``forward`` is run on the tensordict with its ``in_keys``
        computed.)"""
        if type(self).forward is not RolloutCost.forward:
            td = rollout.materialized(self.in_keys or None)
            out = self(td)
            return td if out is None else out
        return self.forward(rollout)

    def forward(self, rollout: TensorDictBase | CandidateRollout) -> TensorDictBase:
        candidates = CandidateRollout.of(rollout)
        candidates.set(self.out_key, self.per_step_cost(candidates))
        return candidates.td

    def extra_repr(self) -> str:
        return f"out_key={self.out_key!r}, step_aggregation={self.step_aggregation!r}"
