"""The checks the DORP policy makes of its parts when it is built.

Each names the part that does not fit and what was expected, so that a policy put
together by hand (another encoder, a planner with another cost) fails at construction
rather than at its first step.
"""

from __future__ import annotations

from torch import nn

from dorp_rl.planners.base import DiscreteMPCPlanner
from dorp_rl.planners.code_graph import CodeGraph
from dorp_rl.policies.action_priors import check_action_prior
from dorp_rl.policies.config import DORPConfig
from dorp_rl.policies.state import GOAL_PRIOR_KEY, PRIOR_KEY

__all__ = ["check_policy_parts"]


def check_policy_parts(
    encoder: nn.Module,
    graph: CodeGraph,
    waypoint_planner: DiscreteMPCPlanner,
    goal_planner: DiscreteMPCPlanner,
    config: DORPConfig,
    goal_pixels_key: str,
) -> None:
    """Raises ``ValueError`` naming the first part of a DORP policy that does not fit.

    Checked: the graph and the encoder (a :class:`~dorp_rl.planners.CodeGraph` built
    with this encoder's codes); the planners (:class:`~dorp_rl.planners.DiscreteMPCPlanner`
    with their own state keys, the waypoint planner's cost reading ``subgoal_code`` and
    ``subgoal_mask``, the goal planner's ``goal_pixels_key``); the config against them
    (``order`` lists every group, ``goal_code_weight`` has a cost term to weigh, an action
    prior has a planner that samples from it and the parts to make it).
    """
    if not isinstance(graph, CodeGraph):
        raise ValueError(f"graph must be a dorp_rl CodeGraph, got {type(graph).__name__}.")
    if not callable(encoder) or not hasattr(encoder, "code_sizes"):
        raise ValueError(
            f"encoder must be callable and have code_sizes, got {type(encoder).__name__}."
        )
    graph.check_encoder(encoder)
    for name, planner in (("waypoint_planner", waypoint_planner), ("goal_planner", goal_planner)):
        if not isinstance(planner, DiscreteMPCPlanner):
            raise ValueError(
                f"{name} must be a dorp_rl DiscreteMPCPlanner, got {type(planner).__name__}."
            )
    if waypoint_planner.plan_key == goal_planner.plan_key:
        raise ValueError(
            "waypoint_planner and goal_planner share their state keys "
            f"({waypoint_planner.plan_key!r}): give them different key_prefix values."
        )
    for key in ("subgoal_code", "subgoal_mask"):
        if key not in waypoint_planner.in_keys:
            raise ValueError(
                f"the waypoint planner's cost must read {key!r} (CodeMatchCost(encoder, "
                f"'subgoal_code', onehots='subgoal_mask')); it reads {waypoint_planner.in_keys}."
            )
    if goal_pixels_key not in goal_planner.in_keys:
        raise ValueError(
            f"the goal planner's cost must read {goal_pixels_key!r} (PixelDistanceCost); "
            f"it reads {goal_planner.in_keys}."
        )
    if not isinstance(config.order, str) and sorted(config.order) != list(range(graph.num_groups)):
        raise ValueError(
            f"order must list every group index 0..{graph.num_groups - 1} once, "
            f"got {list(config.order)}."
        )
    if config.goal_code_weight > 0 and "goal_code_weight" not in goal_planner.in_keys:
        raise ValueError(
            f"goal_code_weight={config.goal_code_weight} but the goal planner's cost "
            "does not read 'goal_code_weight' (use WeightedCostSum({..., "
            "'goal_code_cost': 'goal_code_weight'}) or set goal_code_weight=0)."
        )
    counted = graph.action_counts is not None
    check_action_prior(
        "action_prior_mix",
        config.action_prior_mix or 0.0,
        waypoint_planner,
        PRIOR_KEY,
        None
        if counted
        else "a graph with the play data's action counts (CodeGraph.from_play_data "
        "records them); this one has none: rebuild it, or",
    )
    has_maps = callable(getattr(encoder, "object_maps", None))
    check_action_prior(
        "goal_action_prior_mix",
        config.goal_action_prior_mix or 0.0,
        goal_planner,
        GOAL_PRIOR_KEY,
        None
        if counted and has_maps
        else "a graph with the play data's action counts and an encoder with "
        "object_maps (a DiscreteCodeEncoder):",
    )
