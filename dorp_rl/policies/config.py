"""The DORP policy's settings as one config: the loop, its recovery rules and its planners.

:class:`DORPConfig` is what :func:`~dorp_rl.policies.make_dorp_policy` builds a policy
from. Its defaults are the generic recipe; an env profile's ``dorp`` (a dict of these
fields, :attr:`~dorp_rl.envs.EnvProfile.dorp`) overrides them for the envs it suits
(:meth:`DORPConfig.for_env`), and explicit arguments override both. Measured effects of
each setting are in docs/NOTES.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

from dorp_rl.config import Choice, ConfigMixin, Flag, Float, Int, checked
from dorp_rl.planners.costs import check_step_penalty
from dorp_rl.validation import check_float

__all__ = ["DORPConfig", "ORDERS"]

#: Orders in which groups are moved (besides an explicit sequence of group indices).
ORDERS = ("index", "nearest")


def _order(name: str, value: Any) -> str | tuple[int, ...]:
    if isinstance(value, str):
        if value not in ORDERS:
            raise ValueError(f"{name} must be one of {ORDERS} or group indices, got {value!r}.")
        return value
    if not isinstance(value, Sequence):
        raise ValueError(f"{name} must be one of {ORDERS} or group indices, got {value!r}.")
    return tuple(Int(low=0)(f"{name}[{i}]", g) for i, g in enumerate(value))


def _reenter(name: str, value: Any) -> bool | str:
    if isinstance(value, bool) or type(value).__name__ == "bool_":
        return bool(value)
    if value != "goal":
        raise ValueError(f"{name} must be True, False or 'goal', got {value!r}.")
    return value


def _sigmas(name: str, value: Any) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise ValueError(f"{name} must be a sequence of blur widths, got {value!r}.")
    return tuple(
        check_float(f"{name}[{i}]", s, low=0.0, low_open=True) for i, s in enumerate(value)
    )


def _step_penalty(name: str, value: Any) -> float:
    return check_step_penalty(value, name)


@dataclass
class DORPConfig(ConfigMixin):
    """Settings of the DORP policy (:class:`~dorp_rl.policies.AbstractGoalPolicy` and the
    planners :func:`~dorp_rl.policies.make_dorp_policy` gives it).

    Examples:
        >>> from dorp_rl.policies import DORPConfig
        >>> DORPConfig.for_env("key-wall").reenter
        True
        >>> DORPConfig(waypoint_budget=0)
        Traceback (most recent call last):
        ...
        ValueError: waypoint_budget must be >= 1, got 0.
    """

    # the paper's loop
    order: str | tuple[int, ...] = checked("index", _order)
    """which group moves first: 'index' (index order, as the authors), 'nearest' (the
    shortest path first) or every group index once"""
    waypoint_budget: int = checked(28, Int(low=1))
    """env steps to reach one waypoint before its edge is removed for the task"""
    max_removed_edges: int = checked(128, Int(low=0))
    """edges a task may remove (re-entries included) without reaching a waypoint in
    between; one more failure ends the task"""
    goal_budget: int | None = checked(None, Int(low=1, optional=True))
    """steps the goal-image phase may take before the task is given up (twice that once
    relaxed); None: only the env's step limit"""
    # recovery rules (dorp_rl.policies.recovery)
    max_misses: int | None = checked(1, Int(low=1, optional=True))
    """waypoint plans in a row that reach the waypoint nowhere after which its edge is
    removed at once (None: only the budget counts)"""
    miss_threshold: float = checked(0.5, Float())
    """the plan cost from which a waypoint plan is a miss (CodeMatchCost: no candidate
    reaches the waypoint)"""
    replan_on_miss: bool = checked(False, Flag())
    """follow a missing plan for one step, then plan again (False: to its end)"""
    forget_blocked_edges: bool = checked(True, Flag())
    """a group reaching a waypoint frees the edges removed for the other groups (False:
    every removal holds for the task, as the authors)"""
    restore_when_stuck: bool = checked(True, Flag())
    """with no path left but edges removed, restore them and search again, once until a
    waypoint is reached (False: give up at once, as the authors)"""
    reenter: bool | str = checked(False, _reenter)
    """re-enter a code another way before removing a failed hop that no other path
    replaces, and when the goal phase stalls in it; 'goal': only the latter"""
    max_reentries: int = checked(8, Int(low=0))
    """re-entries a task may start"""
    avoid_noops: bool | None = checked(None, Flag(optional=True))
    """an action that left a frame unchanged does not start a plan from that frame again
    (a learned model may believe a blocked move goes through; assumes a
    deterministic env). None: off with low_level 'gt' (the acting env's own dynamics
    never predict a move that does not happen), on with any other low level"""
    noop_memory: int = checked(32, Int(low=1))
    """avoid_noops: frames per acting env whose unchanging actions are remembered (1: the
    current frame's only, forgotten once the frame changes)"""
    goal_code_weight: float = checked(100.0, Float(low=0.0))
    """goal phase: cost of a frame whose codes are not the goal's, added to its pixel
    distance (0: pixel distance alone, as the paper)"""
    goal_map_weight: float | None = checked(None, Float(low=0.0, optional=True))
    """goal phase: weight of the distance of the encoder's object maps to the goal
    image's (:class:`~dorp_rl.planners.ObjectMapCost`), added to the pixel distance:
    each object is pulled to its own place (None: 4 when the encoder has
    ``object_maps``, else 0)"""
    goal_latent_weight: float | None = checked(None, Float(low=0.0, optional=True))
    """goal phase, when the planning env imagines latent states (it names its model as
    ``latent_model``, as :class:`~dorp_rl.envs.LatentModelEnv` does): weight of the
    distance of each imagined latent to the goal image's
    (:class:`~dorp_rl.planners.LatentGoalCost`). Above 0 it replaces the pixel and
    object-map terms, so the goal phase decodes no frames; 0 judges the goal image on
    decoded frames (None: 1 with such an env, else 0). The waypoint cost's goal term
    (waypoint_goal_weight) is that distance with such an env either way"""
    goal_patience: int | None = checked(14, Int(low=1, optional=True))
    """goal-phase steps without a lower plan cost after which the goal-code term is
    dropped (None: never)"""
    max_goal_returns: int = checked(0, Int(low=0))
    """times a task's relaxed goal phase, stalled again while a code is not the goal's,
    may go back to the code graph with the code term restored (0: it stays relaxed)"""
    # planners
    planner: str = checked("rs", Choice(("rs", "cem")))
    """waypoint planner: 'rs' (random shooting) or 'cem' (categorical CEM)"""
    goal_planner: str | None = checked(None, Choice(("rs", "cem"), optional=True))
    """goal-image planner (None: as planner)"""
    planning_horizon: int = checked(14, Int(low=1))
    """steps per candidate action sequence"""
    num_candidates: int = checked(1000, Int(low=1))
    """candidate action sequences per plan"""
    action_repeat: int = checked(1, Int(low=1))
    """env steps each planned action is held"""
    action_persistence: float | None = checked(
        None, Float(low=0.0, high=1.0, high_open=True, optional=True)
    )
    """random shooting: probability that a sampled action repeats the one before it
    (None: 0.5; 0: uniform draws, as the paper)"""
    goal_blur_sigmas: tuple[float, ...] = checked((1.0, 2.0, 4.0, 8.0), _sigmas)
    """blurred terms of the goal image's pixel distance (): the paper's plain L2)"""
    waypoint_goal_weight: float = checked(0.0, Float(low=0.0))
    """weight of the goal image's pixel distance in the waypoint cost: ranks plans that
    reach the waypoint by how close their frame is to the goal (0: the code match alone)"""
    waypoint_step_penalty: float = checked(0.002, _step_penalty)
    """waypoint cost per step of a frame at the waypoint: earlier arrival wins (0: any
    step reaching the waypoint scores alike)"""
    waypoint_first_arrival: bool = checked(True, Flag())
    """judge a waypoint plan at its first step that reaches the waypoint, where the policy
    stops following it (False: at its best step, which may come later and never run)"""
    prune_plans: bool = checked(True, Flag())
    """drop the decisions of each best plan whose removal lowers its cost or reaches it
    earlier (detours random candidates carry; ``DiscreteMPCPlanner(prune=True)``; False:
    the best sampled sequence as it is, as the paper)"""
    action_prior_mix: float | None = checked(None, Float(low=0.0, high=1.0, optional=True))
    """share of the waypoint planner's actions drawn from those that changed the hop's
    one-hots in the play data (None: 0.8 when the graph has action counts, else 0)"""
    goal_action_prior_mix: float | None = checked(None, Float(low=0.0, high=1.0, optional=True))
    """share of the goal planner's actions drawn from those that changed, in the play
    data, the one-hots whose object maps are still off the goal image's (None: 0.5 when
    the encoder has object maps and the graph action counts, else 0; 0: uniform draws)"""

    #: What a field left ``None`` takes where it suits the env, the graph and the encoder
    #: (each field's text says where; 0 or off elsewhere): the one place of these values.
    #: The ``dorp`` command stores them with each evaluation, beside the config, so a
    #: change here runs stored evaluations again.
    WHERE_SUITED: ClassVar[Mapping[str, float]] = MappingProxyType(
        {
            "action_prior_mix": 0.8,
            "goal_action_prior_mix": 0.5,
            "action_persistence": 0.5,
            "goal_map_weight": 4.0,
            "goal_latent_weight": 1.0,
        }
    )

    @classmethod
    def for_env(cls, env: Any, *, num_objects: int | None = None, **overrides: Any) -> DORPConfig:
        """The config that suits ``env`` (an env, a profile or its name): the profile's
        ``dorp`` over the defaults, then ``overrides``. For a profile that counts objects
        the count is ``num_objects``, else an env's own ``num_objects``, else the
        profile's default count (a name's settings may differ by count: rearrangement's
        from 5 blocks on)."""
        from dorp_rl.envs.profile import EnvProfile, env_profile, profile_of

        named = isinstance(env, (str, EnvProfile))
        profile = env_profile(env) if named else profile_of(env)
        suited: dict[str, Any] = {}
        if profile is not None:
            if num_objects is None and profile.counts_objects and not named:
                num_objects = getattr(env, "num_objects", None)
            suited = profile.dorp_overrides(num_objects if profile.counts_objects else None)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(suited) - known)
        if unknown:
            raise ValueError(
                f"the dorp settings of env profile {profile.name!r} name {unknown}, which are "
                f"no DORPConfig fields ({', '.join(sorted(known))})."
            )
        return cls(**{**suited, **overrides})
