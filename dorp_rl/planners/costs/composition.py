"""Costs made of costs: a sequence of cost modules (:class:`CostSequence`), a weighted
sum (:class:`WeightedCostSum`) and a plan judged where it first reaches its target
(:class:`FirstArrival`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import TensorDictSequential

from dorp_rl.planners.costs.base import (
    MissingRolloutKeyError,
    RolloutCost,
    get_rollout_key,
    score_rollout,
)
from dorp_rl.planners.rollout import CandidateRollout
from dorp_rl.validation import check_float

__all__ = [
    "CostSequence",
    "FirstArrival",
    "WeightedCostSum",
]


class CostSequence(TensorDictSequential):
    """A :class:`~tensordict.nn.TensorDictSequential` of costs run on one rollout.

    Each cost in turn, in the order given, on the same
    :class:`~dorp_rl.planners.CandidateRollout` (:func:`score_rollout`): frames a
    planning env left lazy (``("next", "pixels")`` of
    :class:`~dorp_rl.envs.GroundTruthModelEnv` as undrawn
    :class:`~dorp_rl.envs.planning.ImaginedFrames`) stay lazy for the costs that read
    them for less. A plain ``TensorDictSequential`` works with the planners too, with
    every value it reads computed first. The costs are given in order
    (``CostSequence(a, b, c)`` or one list), not as a mapping.

    Examples:
        >>> from dorp_rl.planners import CostSequence, PixelDistanceCost, WeightedCostSum
        >>> cost = CostSequence(
        ...     PixelDistanceCost(out_key="near"),
        ...     PixelDistanceCost(out_key="blurred", blur_sigmas=(2.0,)),
        ...     WeightedCostSum({"near": 1.0, "blurred": 0.5}),
        ... )
        >>> cost.in_keys, cost.out_keys[-1]
        ([('next', 'pixels'), 'goal_pixels'], 'cost')
    """

    def __init__(self, *costs: Callable) -> None:
        if len(costs) == 1 and isinstance(costs[0], Mapping):
            raise ValueError(
                "CostSequence takes its costs in order, CostSequence(cost_a, cost_b, ...), "
                "not as a mapping of names."
            )
        super().__init__(*costs)

    def forward(self, rollout: TensorDictBase, *args: Any, **kwargs: Any) -> TensorDictBase:
        if args or kwargs:
            return super().forward(rollout, *args, **kwargs)
        return self.score(CandidateRollout.of(rollout))

    def score(self, rollout: CandidateRollout) -> TensorDictBase:
        """Runs the costs in order on ``rollout``; returns its tensordict.

        A term that only the last member (a :class:`WeightedCostSum`) reads, weighted by
        a per-row weight that is 0 in every row, is not computed: it is written as zeros
        (the goal phase's code term once every row dropped it).
        """
        unread = self._terms_read_by_sum_only()
        for index in range(len(self)):
            member = self[index]
            weight_key = unread.get(index)
            if weight_key is not None:
                weight = rollout.get(weight_key, None)
                if weight is not None and not weight.any():
                    shape = rollout.batch_size
                    rollout.set(member.out_key, torch.zeros(shape, device=weight.device))
                    continue
            out = score_rollout(member, rollout)
            if out is not rollout.td:  # a member that returned another tensordict
                rollout = CandidateRollout(out, rollout.lazy)
        return rollout.td

    def _terms_read_by_sum_only(self) -> dict[int, NestedKey]:
        """Index of each cost whose one output only a final :class:`WeightedCostSum`
        reads, weighted by a per-row key -> that key."""
        total = self[len(self) - 1]
        if not isinstance(total, WeightedCostSum):
            return {}
        out: dict[int, NestedKey] = {}
        for index in range(len(self) - 1):
            member = self[index]
            if not isinstance(member, RolloutCost) or len(member.out_keys) != 1:
                continue
            weight = total.weights.get(member.out_key)
            if weight is None or isinstance(weight, float):
                continue
            readers = [m for m in list(self)[index + 1 : -1] if member.out_key in m.in_keys]
            if not readers:
                out[index] = weight
        return out


class WeightedCostSum(RolloutCost):
    """Writes ``sum_k weights[k] * rollout[k]``: a weighted sum of per-step costs.

    The last module of a :class:`CostSequence` (or any
    :class:`~tensordict.nn.TensorDictSequential`) of costs, each writing its per-step
    cost under its own ``out_key``. The sequence's ``in_keys`` are
    the keys its costs read from the rollout (not the intermediate cost keys), which is
    what a planner needs; its last out key (this module's ``out_key``) is the one the
    planner reads by default. A sequence has no ``step_aggregation`` attribute, so pass
    ``step_aggregation=`` to the planner unless ``"sum"`` is wanted.

    Args:
        weights: per-step cost key -> weight: a number, or the key of a per-row weight
            (``[*B, 1]`` in the acting tensordict, carried into the rollout), so a policy
            can turn a term up or down for one env without another cost module.
        out_key: where the weighted sum ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (default ``"sum"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import (
        ...     CodeMatchCost, CostSequence, PixelDistanceCost, WeightedCostSum
        ... )
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> cost = CostSequence(
        ...     PixelDistanceCost(out_key="pixel_cost"),
        ...     CodeMatchCost(encoder, out_key="code_cost"),
        ...     WeightedCostSum({"pixel_cost": 1.0, "code_cost": 0.5}),
        ... )
        >>> cost.in_keys
        [('next', 'pixels'), 'goal_pixels', 'pixels', 'subgoal_code']
        >>> cost.out_keys
        ['pixel_cost', 'code_cost', 'cost']
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> start = frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16)
        >>> rollout = TensorDict(
        ...     {
        ...         "pixels": start,
        ...         "goal_pixels": start,
        ...         "subgoal_code": torch.zeros(2, 1, 1, 2, dtype=torch.int64).expand(2, 5, 4, 2),
        ...         ("next", "pixels"): frames,
        ...     },
        ...     batch_size=(2, 5, 4),
        ... )
        >>> out = cost(rollout)
        >>> torch.allclose(out["cost"], out["pixel_cost"] + 0.5 * out["code_cost"])
        True
    """

    def __init__(
        self,
        weights: Mapping[NestedKey, float | NestedKey],
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "sum",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not isinstance(weights, Mapping) or not weights:
            raise ValueError(
                f"weights must be a non-empty mapping from per-step cost keys to weights, "
                f"got {weights!r}."
            )
        self.weights: dict[NestedKey, float | NestedKey] = {}
        for key, weight in weights.items():
            key = unravel_key(key)
            if key in self.weights:
                raise ValueError(f"weights names the key {key!r} twice.")
            if isinstance(weight, (str, tuple)):
                self.weights[key] = unravel_key(weight)
                continue
            if (
                isinstance(weight, bool)
                or not isinstance(weight, (int, float))
                or not math.isfinite(float(weight))
            ):
                raise ValueError(
                    f"the weight of {key!r} must be a finite number or the key of a per-row "
                    f"weight, got {weight!r}."
                )
            self.weights[key] = float(weight)
        weight_keys = [w for w in self.weights.values() if not isinstance(w, float)]
        self.in_keys = list(dict.fromkeys([*self.weights, *weight_keys]))

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        name = type(self).__name__
        total = None
        for key, weight in self.weights.items():
            value = rollout.get(key, None)
            if value is None:
                raise MissingRolloutKeyError(
                    f"{name} needs the per-step cost {key!r}, which is missing "
                    f"from the rollout: put a cost with out_key={key!r} before it in the "
                    "CostSequence (TensorDictSequential)."
                )
            value = value.to(torch.float32)
            if isinstance(weight, float):
                value = weight * value
            else:
                factor = get_rollout_key(rollout, weight, name).to(torch.float32)
                if factor.numel() != value.numel():
                    raise ValueError(
                        f"the weight {weight!r} must hold one number per row of the acting "
                        f"tensordict ([*B, 1]), got shape {list(factor.shape)} in a rollout "
                        f"of {list(rollout.batch_size)}."
                    )
                value = factor.reshape(value.shape) * value
            total = value if total is None else total + value
        return total

    def extra_repr(self) -> str:
        return f"weights={self.weights!r}, {super().extra_repr()}"


class FirstArrival(RolloutCost):
    """Ends each candidate at the first step a target term calls reached: later steps cost ``inf``.

    A policy that stops following a plan once its target is reached (DORP's waypoints)
    executes only the plan's steps up to that first arrival, so that is where a plan
    should be judged: folded with ``"min"``, a candidate's score is then its cost at the
    first arrival (or its best step if it never arrives), not at a later step that
    would never run. Steps up to and including the first arrival keep ``cost_key``'s
    values.

    Args:
        reached_key: the per-step term ``[*B, N, H]`` that says whether the target is
            reached (e.g. a :class:`CodeMatchCost`'s out key: below ``threshold``).
        cost_key: the per-step cost ``[*B, N, H]`` to cut.
        threshold: a step is an arrival when ``reached_key`` is below it.
        out_key: where the cut cost is written (default: over ``cost_key``).
        step_aggregation: how planners fold the steps (default ``"min"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import FirstArrival
        >>> rollout = TensorDict(
        ...     {"code_cost": torch.tensor([[1.0, 0.0, 0.0, 1.0]]),
        ...      "cost": torch.tensor([[1.2, 0.1, 0.05, 1.0]])},
        ...     batch_size=(1, 4),
        ... )
        >>> FirstArrival("code_cost")(rollout)["cost"]
        tensor([[1.2000, 0.1000,    inf,    inf]])
    """

    def __init__(
        self,
        reached_key: NestedKey,
        *,
        cost_key: NestedKey = "cost",
        threshold: float = 0.5,
        out_key: NestedKey | None = None,
        step_aggregation: str = "min",
    ) -> None:
        cost_key = unravel_key(cost_key)
        super().__init__(
            out_key=cost_key if out_key is None else out_key, step_aggregation=step_aggregation
        )
        self.reached_key = unravel_key(reached_key)
        self.cost_key = cost_key
        self.threshold = check_float("threshold", threshold)
        self.in_keys = list(dict.fromkeys([self.cost_key, self.reached_key]))

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        name = type(self).__name__
        cost = get_rollout_key(rollout, self.cost_key, name).to(torch.float32)
        reached = get_rollout_key(rollout, self.reached_key, name).reshape(cost.shape)
        hit = (reached < self.threshold).to(torch.int64)
        after = (hit.cumsum(-1) - hit) > 0  # an arrival at an earlier step
        return cost.masked_fill(after, math.inf)

    def extra_repr(self) -> str:
        return (
            f"reached_key={self.reached_key!r}, threshold={self.threshold}, {super().extra_repr()}"
        )
