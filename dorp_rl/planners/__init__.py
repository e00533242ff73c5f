"""Planning: discrete MPC planners (random shooting, categorical CEM) and rollout costs.

The planners are :class:`torchrl.modules.planners.MPCPlannerBase` subclasses that
sample discrete action sequences, roll them out in a planning env
(:class:`dorp_rl.envs.GroundTruthModelEnv`, :class:`dorp_rl.envs.WorldModelEnv`) and
minimise a cost module over the imagined rollout.
"""

from dorp_rl.planners.costs import (
    REDUCTIONS,
    CodeMatchCost,
    MissingRolloutKeyError,
    NegativeRewardCost,
    PixelDistanceCost,
    RolloutCost,
    SumCost,
)
from dorp_rl.planners.mpc import (
    EXECUTIONS,
    CategoricalCEMPlanner,
    DiscreteMPCPlanner,
    RandomShootingPlanner,
    reduce_steps,
    select_best,
)

__all__ = [
    "CategoricalCEMPlanner",
    "CodeMatchCost",
    "DiscreteMPCPlanner",
    "EXECUTIONS",
    "MissingRolloutKeyError",
    "NegativeRewardCost",
    "PixelDistanceCost",
    "REDUCTIONS",
    "RandomShootingPlanner",
    "RolloutCost",
    "SumCost",
    "reduce_steps",
    "select_best",
]
