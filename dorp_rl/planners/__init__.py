"""Planning: code graphs, discrete MPC planners (random shooting, categorical CEM), costs.

The planners are :class:`torchrl.modules.planners.MPCPlannerBase` subclasses, one per
file as in torchrl (``base.py``, ``random_shooting.py``, ``cem.py``), that sample
discrete action sequences, roll them out in a planning env
(:class:`dorp_rl.envs.GroundTruthModelEnv`, :class:`dorp_rl.envs.WorldModelEnv`) and
minimise a cost over the imagined rollout. Costs (``costs.py``) are TensorDict modules
that write a per-step cost ``[B, N, H]``; they compose with
:class:`~tensordict.nn.TensorDictSequential` and :class:`WeightedCostSum`.
:class:`CodeGraph` (``code_graph.py``) holds which codes follow each other in play data
and finds DORP's shortest paths over them.
"""

from dorp_rl.planners.base import (
    EXECUTIONS,
    DiscreteMPCPlanner,
    aggregate_steps,
    finished_rows,
    select_best,
)
from dorp_rl.planners.cem import CategoricalCEMPlanner
from dorp_rl.planners.code_graph import (
    CodeGraph,
    encode_transitions,
    encoder_fingerprint,
    resolve_groups,
)
from dorp_rl.planners.costs import (
    STEP_AGGREGATIONS,
    CodeMatchCost,
    MissingRolloutKeyError,
    NegativeRewardCost,
    PixelDistanceCost,
    RolloutCost,
    WeightedCostSum,
    check_step_aggregation,
)
from dorp_rl.planners.random_shooting import RandomShootingPlanner

__all__ = [
    "EXECUTIONS",
    "STEP_AGGREGATIONS",
    "CategoricalCEMPlanner",
    "CodeGraph",
    "CodeMatchCost",
    "DiscreteMPCPlanner",
    "MissingRolloutKeyError",
    "NegativeRewardCost",
    "PixelDistanceCost",
    "RandomShootingPlanner",
    "RolloutCost",
    "WeightedCostSum",
    "aggregate_steps",
    "check_step_aggregation",
    "encode_transitions",
    "encoder_fingerprint",
    "finished_rows",
    "resolve_groups",
    "select_best",
]
