"""Costs of imagined rollouts: TensorDict modules that the discrete MPC planners minimise.

A planner rolls ``N`` candidate action sequences of ``H`` steps out for each of ``B``
acting envs and hands the cost one tensordict of batch shape ``[B, N, H]``:

- ``action``: int64 ``[B, N, H, 1]``, the action taken at each step;
- ``("next", key)``: what the planning env produced after each step, e.g.
  ``("next", "pixels")`` uint8 ``[B, N, H, C, H', W']``, the predicted frames;
- any other root key: the acting env's tensordict at planning time (the start of the
  rollout), broadcast without copies over candidates and steps. So root ``pixels`` is
  the *start* frame at every step, and ``goal_pixels`` / ``subgoal_code`` are the goal
  of each row.

Each cost is a :class:`~tensordict.nn.TensorDictModuleBase`: it reads its ``in_keys``
and writes a per-step cost, float ``[B, N, H]`` (lower is better), under its
``out_key`` (``"cost"`` by default), so costs compose like any TensorDict modules, best
in a :class:`CostSequence` (a ``TensorDictSequential`` run on one rollout)::

    CostSequence(
        PixelDistanceCost(out_key="pixel_cost"),
        CodeMatchCost(encoder, out_key="code_cost"),
        WeightedCostSum({"pixel_cost": 1.0, "code_cost": 0.5}),  # writes "cost"
    )

One rollout
    The planner hands the cost a :class:`~dorp_rl.planners.CandidateRollout`, whatever
    the planning env: ``rollout.get(key)`` gives a tensor, ``rollout.frames(key)`` the
    frames, held (a stepped env's) or imagined and drawn only when needed (the true
    dynamics' undrawn :class:`~dorp_rl.envs.planning.ImaginedFrames`), with one
    interface for both: their distinct frames by the one frame hash, and exact distances
    to goal images where the env gives them without drawing. So each cost has one
    implementation, :meth:`RolloutCost.per_step_cost`. :func:`score_rollout` runs any
    cost module on a rollout (a module that is not a :class:`RolloutCost` gets the
    values it reads computed into the tensordict); called on a plain tensordict, a cost
    reads it as a rollout with nothing lazy.

A cost also says, with its ``step_aggregation``, how a planner should fold the ``H``
per-step costs of one candidate into that candidate's score (it is not a loss
reduction: it decides which sequence is best and how much of it runs open loop):

- ``"min"``: the best step counts. A sequence is as good as the closest it gets to the
  goal; in open-loop execution the planner then executes the sequence only up to that
  step (the authors' release: "execute the prefix with the lowest pixel L2"). This is
  the default of :class:`PixelDistanceCost` and :class:`CodeMatchCost` (a sequence is
  good if it reaches the target code at some step).
- ``"sum"``: every step counts (the total along the way).
- ``"final"``: only the last step counts.

The planner uses ``in_keys`` (for a :class:`CostSequence` or any
:class:`~tensordict.nn.TensorDictSequential`, the keys read and not produced inside it) to stack only the predictions that are needed
and to check, before rolling out, that every key is there. A key missing from the
rollout raises :class:`MissingRolloutKeyError` (both a ``KeyError`` and a
``ValueError``) naming it.
"""

from dorp_rl.planners.costs.base import (
    STEP_AGGREGATIONS,
    MissingRolloutKeyError,
    RolloutCost,
    check_step_aggregation,
    score_rollout,
)
from dorp_rl.planners.costs.code_match import CodeMatchCost, check_step_penalty
from dorp_rl.planners.costs.composition import CostSequence, FirstArrival, WeightedCostSum
from dorp_rl.planners.costs.goal_image import LatentGoalCost, ObjectMapCost, PixelDistanceCost
from dorp_rl.planners.costs.reward import NegativeRewardCost

__all__ = [
    "STEP_AGGREGATIONS",
    "CodeMatchCost",
    "CostSequence",
    "FirstArrival",
    "LatentGoalCost",
    "MissingRolloutKeyError",
    "NegativeRewardCost",
    "ObjectMapCost",
    "PixelDistanceCost",
    "RolloutCost",
    "WeightedCostSum",
    "check_step_aggregation",
    "check_step_penalty",
    "score_rollout",
]
