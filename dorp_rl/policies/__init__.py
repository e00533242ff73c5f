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
from dorp_rl.policies.visual_foresight import VARIANT_DEFAULTS, VisualForesightPolicy

__all__ = [
    "AbstractGoalPolicy",
    "DORP_RECIPE",
    "ENDINGS",
    "MODES",
    "ORDERS",
    "VARIANT_DEFAULTS",
    "VisualForesightPolicy",
    "make_dorp_policy",
    "make_waypoint_cost",
]
