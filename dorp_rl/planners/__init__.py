"""Planning: code graphs, discrete MPC planners (random shooting, categorical CEM), costs.

The planners are :class:`torchrl.modules.planners.MPCPlannerBase` subclasses, one per
file as in torchrl (``base.py``, ``random_shooting.py``, ``cem.py``), that sample
discrete action sequences, roll them out in a planning env
(:class:`dorp_rl.envs.GroundTruthModelEnv`, :class:`dorp_rl.envs.VideoModelEnv`) and
minimise a cost over the imagined rollout, one :class:`CandidateRollout`
(``rollout.py``) whatever the env. Costs (``costs/``) are TensorDict modules that write a
per-step cost ``[B, N, H]``; they compose with :class:`CostSequence` (a
:class:`~tensordict.nn.TensorDictSequential` run on one rollout) and
:class:`WeightedCostSum`. What a planning env declares to imagine candidates in bulk
(``imagine_candidates``) is in ``base.py``'s docstring.
:class:`CodeGraph` (``code_graph.py``) holds which codes follow each other in play data
and finds DORP's shortest paths over them; :func:`coupled_groups` (``coupling.py``) reads
from the play data which one-hots it plans together.
"""

from dorp_rl.planners.base import (
    EXECUTIONS,
    DiscreteMPCPlanner,
    aggregate_steps,
    finished_rows,
    improves,
    select_best,
)
from dorp_rl.planners.cem import CategoricalCEMPlanner
from dorp_rl.planners.code_graph import CodeGraph, resolve_groups
from dorp_rl.planners.costs import (
    STEP_AGGREGATIONS,
    CodeMatchCost,
    CostSequence,
    FirstArrival,
    LatentGoalCost,
    MissingRolloutKeyError,
    NegativeRewardCost,
    ObjectMapCost,
    PixelDistanceCost,
    RolloutCost,
    WeightedCostSum,
    check_step_aggregation,
    score_rollout,
)
from dorp_rl.planners.coupling import GroupChoice, coupled_groups
from dorp_rl.planners.play_codes import encode_transitions, encoder_fingerprint
from dorp_rl.planners.random_shooting import RandomShootingPlanner
from dorp_rl.planners.rollout import CandidateRollout

__all__ = [
    "EXECUTIONS",
    "STEP_AGGREGATIONS",
    "CandidateRollout",
    "CategoricalCEMPlanner",
    "CodeGraph",
    "CodeMatchCost",
    "CostSequence",
    "FirstArrival",
    "GroupChoice",
    "LatentGoalCost",
    "DiscreteMPCPlanner",
    "MissingRolloutKeyError",
    "NegativeRewardCost",
    "ObjectMapCost",
    "PixelDistanceCost",
    "RandomShootingPlanner",
    "RolloutCost",
    "WeightedCostSum",
    "aggregate_steps",
    "check_step_aggregation",
    "coupled_groups",
    "encode_transitions",
    "encoder_fingerprint",
    "finished_rows",
    "resolve_groups",
    "score_rollout",
    "improves",
    "select_best",
]
