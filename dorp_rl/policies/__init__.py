"""Policies: DORP's hierarchical abstract-goal policy and the visual-foresight baselines."""

from dorp_rl.policies.abstract_goal import (
    DORP_RECIPE,
    ENDINGS,
    MODES,
    ORDERS,
    AbstractGoalPolicy,
    make_dorp_policy,
    make_waypoint_cost,
)
from dorp_rl.policies.low_level import TRUE_DYNAMICS, make_planning_env
from dorp_rl.policies.visual_foresight import VARIANT_DEFAULTS, VisualForesightPolicy

__all__ = [
    "AbstractGoalPolicy",
    "DORP_RECIPE",
    "ENDINGS",
    "MODES",
    "ORDERS",
    "TRUE_DYNAMICS",
    "VARIANT_DEFAULTS",
    "VisualForesightPolicy",
    "make_dorp_policy",
    "make_planning_env",
    "make_waypoint_cost",
]
