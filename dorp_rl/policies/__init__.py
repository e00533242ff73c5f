"""Policies: DORP's hierarchical abstract-goal policy and the visual-foresight baselines.

- :mod:`~dorp_rl.policies.abstract_goal`: the paper's loop (:class:`AbstractGoalPolicy`);
- :mod:`~dorp_rl.policies.recovery`: its recovery rules, one part each;
- :mod:`~dorp_rl.policies.state`: the one declaration of a policy's state keys (the
  loop's in :func:`loop_state_keys`);
- :mod:`~dorp_rl.policies.records`: how the policy fared on each task (:func:`task_records`);
- :mod:`~dorp_rl.policies.action_priors`, :mod:`~dorp_rl.policies.checks`: the
  planners' action priors and the checks of the policy's parts;
- :mod:`~dorp_rl.policies.config`: its settings (:class:`DORPConfig`);
- :mod:`~dorp_rl.policies.factory`: :func:`make_dorp_policy`, planners and costs from a config;
- :mod:`~dorp_rl.policies.visual_foresight`, :mod:`~dorp_rl.policies.low_level`.
"""

from dorp_rl.policies.abstract_goal import LOOP_FIELDS, AbstractGoalPolicy
from dorp_rl.policies.config import ORDERS, DORPConfig
from dorp_rl.policies.factory import make_dorp_policy, make_waypoint_cost
from dorp_rl.policies.low_level import TRUE_DYNAMICS, make_planning_env
from dorp_rl.policies.records import task_records
from dorp_rl.policies.recovery import (
    AvoidNoops,
    ForgetBlocked,
    GoalRelaxation,
    MissedPlans,
    RecoveryRule,
    Reentry,
    RestoreWhenStuck,
    RuleContext,
    recovery_rules,
)
from dorp_rl.policies.state import (
    ENDINGS,
    GOAL_PRIOR_KEY,
    MODES,
    NOOPS_KEY,
    PRIOR_KEY,
    PolicyState,
    StateKey,
    loop_state_keys,
)
from dorp_rl.policies.visual_foresight import VARIANT_DEFAULTS, VisualForesightPolicy

__all__ = [
    "AbstractGoalPolicy",
    "AvoidNoops",
    "DORPConfig",
    "ENDINGS",
    "ForgetBlocked",
    "GoalRelaxation",
    "LOOP_FIELDS",
    "MODES",
    "MissedPlans",
    "GOAL_PRIOR_KEY",
    "NOOPS_KEY",
    "PRIOR_KEY",
    "ORDERS",
    "PolicyState",
    "RecoveryRule",
    "Reentry",
    "RestoreWhenStuck",
    "RuleContext",
    "StateKey",
    "TRUE_DYNAMICS",
    "VARIANT_DEFAULTS",
    "VisualForesightPolicy",
    "make_dorp_policy",
    "make_planning_env",
    "make_waypoint_cost",
    "loop_state_keys",
    "recovery_rules",
    "task_records",
]
