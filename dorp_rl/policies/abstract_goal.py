"""DORP's hierarchical policy: a shortest path over codes, followed waypoint by waypoint.

:class:`AbstractGoalPolicy` is the paper's planning loop as one TorchRL policy:

1. encode ``pixels`` and (once per episode) ``goal_pixels`` into codes;
2. pick a group of one-hots whose code differs from the goal's, in a set order;
3. find its shortest path in the :class:`~dorp_rl.planners.CodeGraph`;
4. write the next waypoint as ``subgoal_code`` with ``subgoal_mask`` (the one-hots it
   concerns) and let the low-level planner act with
   :class:`~dorp_rl.planners.CodeMatchCost` (the other one-hots keep their codes);
5. from the real frames reached, check whether the waypoint was reached within its step
   budget; if not, remove that edge for this task and replan; when no group has a path
   left the task ends as failed (``dorp_failed``), never in an endless loop. A learned
   code may cover separate places (two rooms), and a hop may start from only one of
   them: before removing a failed hop that no other path can replace, the group goes
   back out over the edge by which it entered the code, re-enters the code another way
   and tries the hop once more (``reenter``);
6. once every one-hot holds the goal's code, drive to the goal image with
   :class:`~dorp_rl.planners.PixelDistanceCost` while keeping the goal's codes; when
   its plans stop getting closer for ``goal_patience`` steps (a learned code can cover
   two places the planner cannot join without leaving it), the group whose hop entered
   the goal code re-enters it another way if the graph has one (``reenter``), else the
   code term is dropped and pixel distance alone drives the rest; a task that spends more than ``goal_budget``
   steps in this phase (twice that once relaxed) is given up too.

All plan state lives in the tensordict (keys below, ``[*B, ...]`` per env), declared by
:meth:`AbstractGoalPolicy.make_tensordict_primer` and restarted on ``is_init``, so one
instance serves a batch of envs with different goals, partial resets and collector
workers. Rows whose ``done`` is set, or that failed, are not planned for (action 0).

=========================  ==================  ===========================================
key                        dtype / shape       meaning
=========================  ==================  ===========================================
``code``, ``goal_code``    int64 ``[C]``       codes of the current frame and of the goal
``subgoal_code``           int64 ``[C]``       the waypoint (other one-hots: current codes)
``subgoal_mask``           bool ``[C]``        the one-hots the waypoint concerns
``dorp_mode``              int64 ``[1]``       0 new, 1 waypoint, 2 goal image, 3 failed,
                                               4 done (:data:`MODES`)
``dorp_group``             int64 ``[1]``       group being moved
``dorp_distance``          int64 ``[1]``       hops left on its path (incl. the waypoint)
``dorp_budget``            int64 ``[1]``       steps left to reach the waypoint
``dorp_edge``              int64 ``[1]``       graph edge of the current hop (-1: none)
``dorp_removed``           int64 ``[R]``       edges removed for this task (-1: free slot)
``dorp_replans``           int64 ``[1]``       edges removed so far
``dorp_waypoints``         int64 ``[1]``       waypoints reached so far
``dorp_goal_steps``        int64 ``[1]``       steps spent in the goal-image phase
``dorp_waypoint_steps``    int64 ``[1]``       steps spent moving to waypoints
``dorp_plans``             int64 ``[1]``       waypoint plans made (fresh low-level plans)
``dorp_reentries``         int64 ``[1]``       re-entries started
``dorp_end``               int64 ``[1]``       why the policy gave up: 0 not given up, 1 no
                                               path left, 2 goal phase out of budget, 3
                                               edge-removal limit (:data:`ENDINGS`)
``dorp_end_group``         int64 ``[1]``       the group left without a path (-1: none)
``dorp_misses``            int64 ``[1]``       plans for this waypoint that reached it nowhere
``dorp_entry_edge``        int64 ``[1]``       edge of the last hop reached (-1: none)
``dorp_via``               int64 ``[1]``       node being re-entered another way (-1: none)
``dorp_via_ban``           int64 ``[1]``       the entry edge the re-entry must not use
``dorp_via_left``          bool ``[1]``        the group has left ``dorp_via`` on the way
``dorp_reentered``         int64 ``[K]``       edges re-entered for this task (-1: free slot)
``dorp_failed``            bool ``[1]``        no path left: the task is given up
``dorp_restored``          bool ``[1]``        removed edges were restored (no path was
                                               left) since the last waypoint reached
``dorp_goal_best``         float ``[1]``       lowest goal-plan cost so far (``inf``: none)
``dorp_goal_stall``        int64 ``[1]``       goal-phase steps since that cost last fell
``dorp_relaxed``           bool ``[1]``        the goal phase dropped its goal-code term
``goal_code_weight``       float ``[1]``       weight of the goal-code term (read by the
                                               goal planner's cost; 0 once relaxed)
=========================  ==================  ===========================================
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, TensorDictPrimer

from dorp_rl.envs.profile import profile_of
from dorp_rl.envs.spec import DiscreteActions, env_identity
from dorp_rl.modules.encoder import module_device
from dorp_rl.planners.base import DiscreteMPCPlanner, finished_rows
from dorp_rl.planners.cem import CategoricalCEMPlanner
from dorp_rl.planners.code_graph import CodeGraph
from dorp_rl.planners.costs import (
    CodeMatchCost,
    PixelDistanceCost,
    WeightedCostSum,
    check_step_penalty,
)
from dorp_rl.planners.random_shooting import RandomShootingPlanner
from dorp_rl.policies.low_level import make_planning_env
from dorp_rl.validation import (
    MissingKeyError,
    check_bool,
    check_float,
    check_int,
    check_keywords,
    check_seed,
    check_task_frames,
    derive_seed,
    keyword_names,
)

#: Values of ``dorp_mode``.
MODES = {"new": 0, "waypoint": 1, "goal": 2, "failed": 3, "done": 4}
_NEW, _WAYPOINT, _GOAL, _FAILED, _DONE = range(5)
#: Values of ``dorp_end``: why the policy gave a task up (the ``outcome`` of
#: :meth:`AbstractGoalPolicy.task_records`).
ENDINGS = {"running": 0, "no_path": 1, "goal_stalled": 2, "removal_limit": 3}
_RUNNING, _NO_PATH, _GOAL_STALLED, _REMOVAL_LIMIT = range(4)
_CEM_ONLY = frozenset(
    ("optim_steps", "top_k", "warm_start", "warm_start_mix", "smoothing", "min_probability")
)
#: Reset values of the state keys that do not start at 0.
_FILLS = {
    "dorp_removed": -1,
    "dorp_edge": -1,
    "dorp_entry_edge": -1,
    "dorp_via": -1,
    "dorp_via_ban": -1,
    "dorp_reentered": -1,
    "dorp_end_group": -1,
    "subgoal_mask": False,
    "dorp_failed": False,
    "dorp_restored": False,
    "dorp_relaxed": False,
    "dorp_goal_best": float("inf"),
}
_BOOL_KEYS = ("subgoal_mask", "dorp_failed", "dorp_relaxed", "dorp_via_left", "dorp_restored")
_FLOAT_KEYS = ("dorp_goal_best", "goal_code_weight")
#: Where the policy writes the waypoint planner's action distribution (``action_prior_mix``).
PRIOR_KEY = "subgoal_action_prior"
#: The version of :func:`make_dorp_policy`'s defaults, raised whenever they change: the
#: ``dorp`` command records it with each DORP evaluation, so a stored evaluation of an
#: older recipe runs again instead of being reused.
DORP_RECIPE = 3
#: make_dorp_policy's recovery settings for an env whose profile declares none (the
#: profile's ``dorp``, a dict of these keys, overrides them): the paper's loop.
GENERIC_DORP_OPTIONS = {"reenter": False, "replan_on_miss": False, "waypoint_goal_weight": 0.0}
#: make_dorp_policy's ``action_prior_mix`` for graphs with action counts.
DEFAULT_ACTION_PRIOR_MIX = 0.8
#: Orders in which groups are moved (besides an explicit sequence of group indices).
ORDERS = ("index", "nearest")


class AbstractGoalPolicy(TensorDictModuleBase):
    """The DORP policy: code-graph waypoints for a low-level discrete MPC planner.

    See the module docstring for the loop and the keys it keeps.

    Args:
        encoder: maps frames to codes (``forward(pixels) -> (code, probs)`` and
            ``code_sizes``): a trained :class:`~dorp_rl.modules.DiscreteCodeEncoder`
            or an :class:`~dorp_rl.modules.OracleCodeEncoder`.
        graph: a :class:`~dorp_rl.planners.CodeGraph` built with that encoder.
        waypoint_planner: a :class:`~dorp_rl.planners.DiscreteMPCPlanner` whose cost
            reads ``subgoal_code`` and ``subgoal_mask`` (a
            :class:`~dorp_rl.planners.CodeMatchCost` with ``onehots="subgoal_mask"``).
        goal_planner: a planner whose cost reads ``goal_pixels`` (a
            :class:`~dorp_rl.planners.PixelDistanceCost`), with another ``key_prefix``.
        order: ``"index"`` (groups in index order, as the authors), ``"nearest"`` (the
            group with the shortest path first) or a sequence of group indices.
        waypoint_budget: env steps allowed to reach one waypoint before its edge is
            removed for the task.
        max_removed_edges: edges a task may remove; one more failure ends the task.
            With five blocks, hops often fail because another block is in the way:
            with ``make_dorp_policy``'s defaults, 5-object tasks removed about 13 edges
            each.
        goal_budget: steps the goal-image phase may take in all before the task is
            given up (``None``: no limit but the env's). Pixel distance can get stuck
            where a goal code spans a region the planner cannot cross within its horizon
            (key rooms: a code on both sides of a wall); giving up frees the planning.
        max_misses: waypoint plans in a row whose best candidate costs at least
            ``miss_threshold`` (none reaches the waypoint, for a
            :class:`~dorp_rl.planners.CodeMatchCost`) after which the edge is removed
            without waiting for the budget (``None``: only the budget counts).
        miss_threshold: the plan cost from which a waypoint plan is a miss.
        replan_on_miss: after a miss, take the plan's first step only and plan again
            (``False``: follow the missing plan to its end, as any other plan).
        goal_code_weight: the weight the goal planner's cost gives the goal-code term,
            written per row under ``goal_code_weight`` (its cost must read that key, as
            :func:`make_dorp_policy` builds it); ``None``: the cost has no such term.
        goal_patience: goal-phase steps without a lower goal-plan cost after which the
            goal-code term is dropped for the task (``None``: never; needs
            ``goal_code_weight``).
        forget_blocked_edges: when a group reaches a waypoint, restore the edges removed
            for the other groups (their hops may have failed only because an object
            stood in the way, which has now moved); ``False`` keeps every removal for the
            rest of the task, as the authors.
        restore_when_stuck: when no group has a path to its goal code left but edges were
            removed, restore all of them and plan again instead of giving the task up
            (a hop removed because an object stood in the way may be the group's only
            way). At most once until a waypoint is reached again, so a goal behind an
            edge that never works is still given up; the removals count towards
            ``max_removed_edges``. ``False`` gives up at once, as the authors.
        reenter: when removing a failed hop would leave its group no path to the goal
            code, and the group entered the hop's code by a hop: first go back out over
            that entry edge, re-enter the code another way and try the hop once more (a
            code covering two rooms may join the next code from one of them only). The
            same when the goal phase stalls in a goal code entered by a hop, before the
            code term is dropped. A failure on the way in starts its own re-entry in
            place of the first. Once per edge; it counts as a removal towards
            ``max_removed_edges``. ``"goal"``: only the stalled goal phase re-enters
            (failed hops are removed at once).
        max_reentries: re-entries a task may start (then failed hops are removed at once).
        action_prior_mix: the share of the waypoint planner's sampled actions drawn from
            the actions that changed the hop's one-hots in the play data
            (:meth:`~dorp_rl.planners.CodeGraph.action_weights`), the rest uniformly; 0
            draws uniformly. The waypoint planner must read the distribution from
            ``"subgoal_action_prior"`` (``action_prior_key``) and the graph must have its
            play data's action counts. With many actions of which few move the hop's
            object, uniform draws rarely move it far, and hops fail for want of a
            candidate.

    Examples:
        >>> import torch
        >>> from dorp_rl.data import collect_play_data
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.modules import OracleCodeEncoder
        >>> from dorp_rl.planners import CodeGraph
        >>> from dorp_rl.policies import make_dorp_policy
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> oracle = OracleCodeEncoder(env)
        >>> graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
        >>> policy = make_dorp_policy(env, oracle, graph, num_candidates=200, seed=0)
        >>> td = env.rollout(100, policy, break_when_all_done=True, break_when_any_done=False)
        >>> bool(td["next", "success"].any(-2).all())
        True
    """

    def __init__(
        self,
        encoder: nn.Module,
        graph: CodeGraph,
        waypoint_planner: DiscreteMPCPlanner,
        goal_planner: DiscreteMPCPlanner,
        *,
        order: str | Sequence[int] = "index",
        waypoint_budget: int = 28,
        max_removed_edges: int = 128,
        goal_budget: int | None = 56,
        max_misses: int | None = 1,
        miss_threshold: float = 0.5,
        forget_blocked_edges: bool = True,
        restore_when_stuck: bool = True,
        reenter: bool | str = False,
        max_reentries: int = 8,
        replan_on_miss: bool = False,
        goal_code_weight: float | None = None,
        goal_patience: int | None = 14,
        action_prior_mix: float = 0.0,
        actions: DiscreteActions | None = None,
        pixels_key: str = "pixels",
        goal_pixels_key: str = "goal_pixels",
    ) -> None:
        super().__init__()
        if not isinstance(graph, CodeGraph):
            raise ValueError(f"graph must be a dorp_rl CodeGraph, got {type(graph).__name__}.")
        if not callable(encoder) or not hasattr(encoder, "code_sizes"):
            raise ValueError(
                f"encoder must be callable and have code_sizes, got {type(encoder).__name__}."
            )
        graph.check_encoder(encoder)
        for name, planner in (
            ("waypoint_planner", waypoint_planner),
            ("goal_planner", goal_planner),
        ):
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
        waypoint_budget = check_int("waypoint_budget", waypoint_budget, low=1)
        max_removed_edges = check_int("max_removed_edges", max_removed_edges, low=0)
        goal_budget = check_int("goal_budget", goal_budget, low=1, optional=True)
        max_misses = check_int("max_misses", max_misses, low=1, optional=True)
        miss_threshold = check_float("miss_threshold", miss_threshold)
        forget_blocked_edges = check_bool("forget_blocked_edges", forget_blocked_edges)
        restore_when_stuck = check_bool("restore_when_stuck", restore_when_stuck)
        max_reentries = check_int("max_reentries", max_reentries, low=0)
        replan_on_miss = check_bool("replan_on_miss", replan_on_miss)
        goal_code_weight = check_float("goal_code_weight", goal_code_weight, low=0.0, optional=True)
        goal_patience = check_int("goal_patience", goal_patience, low=1, optional=True)
        action_prior_mix = check_float("action_prior_mix", action_prior_mix, low=0.0, high=1.0)
        if action_prior_mix > 0:
            if waypoint_planner.action_prior_key != PRIOR_KEY:
                raise ValueError(
                    f"action_prior_mix={action_prior_mix} needs a waypoint planner that samples "
                    f"from {PRIOR_KEY!r} (action_prior_key={PRIOR_KEY!r}), got "
                    f"action_prior_key={waypoint_planner.action_prior_key!r}."
                )
            if graph.action_counts is None:
                raise ValueError(
                    f"action_prior_mix={action_prior_mix} needs a graph with the play data's "
                    "action counts (CodeGraph.from_play_data records them); this one has "
                    "none: rebuild it, or pass action_prior_mix=0."
                )
        self.action_prior_mix = float(action_prior_mix)
        if isinstance(order, str):
            if order not in ORDERS:
                raise ValueError(f"order must be one of {ORDERS} or group indices, got {order!r}.")
            self.order: str | list[int] = order
        else:
            self.order = [int(g) for g in order]
            if sorted(self.order) != list(range(graph.num_groups)):
                raise ValueError(
                    f"order must list every group index 0..{graph.num_groups - 1} once, "
                    f"got {list(order)}."
                )
        self.encoder = encoder
        self.graph = graph
        self.waypoint_planner = waypoint_planner
        self.goal_planner = goal_planner
        self.waypoint_budget = waypoint_budget
        self.goal_budget = goal_budget
        self.max_misses = max_misses
        self.miss_threshold = miss_threshold
        self.forget_blocked_edges = forget_blocked_edges
        if isinstance(reenter, bool) or type(reenter).__name__ == "bool_":
            reenter = bool(reenter)
        elif reenter != "goal":
            raise ValueError(f"reenter must be True, False or 'goal', got {reenter!r}.")
        self.reenter = reenter
        self._reenter_hops = reenter is True
        self.max_reentries = max_reentries
        self.replan_on_miss = replan_on_miss
        reads_weight = "goal_code_weight" in goal_planner.in_keys
        if goal_code_weight is not None and not reads_weight:
            raise ValueError(
                "goal_code_weight is given but the goal planner's cost does not read "
                "'goal_code_weight' (use WeightedCostSum({..., 'goal_code_cost': "
                "'goal_code_weight'}) or leave goal_code_weight=None)."
            )
        if reads_weight and goal_code_weight is None:
            raise ValueError(
                "the goal planner's cost reads 'goal_code_weight': give goal_code_weight, "
                "the weight the policy writes there."
            )
        if goal_patience is not None and goal_code_weight is None:
            goal_patience = None  # nothing to relax
        self.goal_code_weight = None if goal_code_weight is None else float(goal_code_weight)
        self.goal_patience = None if goal_patience is None else int(goal_patience)
        self.max_removed_edges = int(max_removed_edges)
        self.restore_when_stuck = restore_when_stuck
        self.pixels_key = pixels_key
        self.goal_pixels_key = goal_pixels_key
        self.num_onehots = len(graph.code_sizes)
        self.state_keys = [
            "code",
            "goal_code",
            "subgoal_code",
            "subgoal_mask",
            "dorp_mode",
            "dorp_group",
            "dorp_distance",
            "dorp_budget",
            "dorp_edge",
            "dorp_removed",
            "dorp_replans",
            "dorp_waypoints",
            "dorp_goal_steps",
            "dorp_misses",
            "dorp_entry_edge",
            "dorp_via",
            "dorp_via_ban",
            "dorp_via_left",
            "dorp_reentered",
            "dorp_failed",
            "dorp_restored",
            "dorp_goal_best",
            "dorp_goal_stall",
            "dorp_relaxed",
            "dorp_waypoint_steps",
            "dorp_plans",
            "dorp_reentries",
            "dorp_end",
            "dorp_end_group",
        ]
        if self.goal_code_weight is not None:
            self.state_keys.append("goal_code_weight")
        planner_keys = [*waypoint_planner.in_keys, *goal_planner.in_keys]
        self.in_keys = list(
            dict.fromkeys(
                [pixels_key, goal_pixels_key, *planner_keys, *self.state_keys, "is_init", "done"]
            )
        )
        #: the acting env's action layout: the planners' indices are written in it
        #: (a one-hot env gets one-hot actions); ``None``: int64 indices ``[*B, 1]``
        self.actions = actions
        self.out_keys = list(
            dict.fromkeys(
                ["action", *self.state_keys, *waypoint_planner.state_keys, *goal_planner.state_keys]
            )
        )

    # ------------------------------------------------------------------ #
    # State declaration
    # ------------------------------------------------------------------ #
    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Declares the policy's own keys (zeros at reset; ``dorp_removed`` and ``dorp_edge`` -1).

        torchrl's collectors find this and the planners' primers when built with
        ``auto_register_policy_transforms=True``; :meth:`make_primer` gives all of them
        for ``env.append_transform``.
        """
        c = self.num_onehots
        r = max(1, self.max_removed_edges)

        def integer(*shape: int) -> Unbounded:
            return Unbounded(shape=shape, dtype=torch.int64)

        specs = Composite(
            code=integer(c),
            goal_code=integer(c),
            subgoal_code=integer(c),
            subgoal_mask=Binary(n=c, shape=(c,), dtype=torch.bool),
            dorp_mode=integer(1),
            dorp_group=integer(1),
            dorp_distance=integer(1),
            dorp_budget=integer(1),
            dorp_edge=integer(1),
            dorp_removed=integer(r),
            dorp_replans=integer(1),
            dorp_waypoints=integer(1),
            dorp_goal_steps=integer(1),
            dorp_misses=integer(1),
            dorp_entry_edge=integer(1),
            dorp_via=integer(1),
            dorp_via_ban=integer(1),
            dorp_via_left=Binary(n=1, shape=(1,), dtype=torch.bool),
            dorp_reentered=integer(max(1, self.max_reentries)),
            dorp_failed=Binary(n=1, shape=(1,), dtype=torch.bool),
            dorp_restored=Binary(n=1, shape=(1,), dtype=torch.bool),
            dorp_goal_best=Unbounded(shape=(1,), dtype=torch.float32),
            dorp_goal_stall=integer(1),
            dorp_relaxed=Binary(n=1, shape=(1,), dtype=torch.bool),
            dorp_waypoint_steps=integer(1),
            dorp_plans=integer(1),
            dorp_reentries=integer(1),
            dorp_end=integer(1),
            dorp_end_group=integer(1),
        )
        if self.goal_code_weight is not None:
            specs["goal_code_weight"] = Unbounded(shape=(1,), dtype=torch.float32)
        defaults = {key: 0 for key in specs.keys()}
        defaults.update(_FILLS)
        return TensorDictPrimer(specs, default_value=defaults, expand_specs=True)

    def make_primer(self) -> Compose:
        """Every key the policy and its planners keep, for ``env.append_transform``."""
        return Compose(
            self.make_tensordict_primer(),
            self.waypoint_planner.make_primer(),
            self.goal_planner.make_primer(),
        )

    def set_seed(self, seed: int | None) -> None:
        """Reseeds both planners (the goal planner with ``seed + 1``)."""
        seed = check_seed(seed, optional=True)
        self.waypoint_planner.set_seed(seed)
        self.goal_planner.set_seed(None if seed is None else derive_seed(seed, 1))

    def task_records(self, last: TensorDictBase) -> list[dict[str, Any]]:
        """How the policy fared on each task, from the tensordicts of the tasks' last steps.

        Args:
            last: ``[N]`` tensordict of one step per task (the step the task ended at),
                holding this policy's state keys.

        Returns:
            One dict per task: ``outcome`` (``"no_path"``, ``"goal_stalled"`` or
            ``"removal_limit"`` when the policy gave the task up, ``None`` when it did
            not), ``group`` (the group left without a path, or whose hop hit the removal
            limit; ``None``), ``phase`` (the :data:`MODES` name at that step), and the
            counts ``edge_removals``, ``reentries``, ``plans`` (waypoint plans made),
            ``waypoints`` (reached), ``waypoint_steps``, ``goal_steps`` and ``relaxed``.
            :func:`~dorp_rl.eval.evaluate_policy` puts them into its ``records``.
        """
        names = {v: k for k, v in ENDINGS.items()}
        phases = {v: k for k, v in MODES.items()}

        def column(key: str) -> list[int]:
            value = last.get(key, None)
            if value is None:
                raise MissingKeyError(
                    f"task_records needs {key!r}: was the step planned by this policy?"
                )
            return value.reshape(last.shape[0], -1)[:, 0].long().tolist()

        ends, groups, modes = column("dorp_end"), column("dorp_end_group"), column("dorp_mode")
        counts = {
            "edge_removals": column("dorp_replans"),
            "reentries": column("dorp_reentries"),
            "plans": column("dorp_plans"),
            "waypoints": column("dorp_waypoints"),
            "waypoint_steps": column("dorp_waypoint_steps"),
            "goal_steps": column("dorp_goal_steps"),
            "relaxed": column("dorp_relaxed"),
        }
        return [
            {
                "outcome": None if ends[i] == _RUNNING else names.get(ends[i], str(ends[i])),
                "group": None if groups[i] < 0 else groups[i],
                "phase": phases.get(modes[i], str(modes[i])),
                **{key: values[i] for key, values in counts.items()},
            }
            for i in range(last.shape[0])
        ]

    # ------------------------------------------------------------------ #
    # Acting
    # ------------------------------------------------------------------ #
    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        flat = tensordict.reshape(-1) if len(batch) != 1 else tensordict
        rows = flat.batch_size[0]
        pixels = self._frames(flat, self.pixels_key)
        goal_pixels = self._frames(flat, self.goal_pixels_key)
        state = {key: self._read(flat, key) for key in self.state_keys}
        mode = state["dorp_mode"].squeeze(-1)

        # New episodes (is_init, or a tensordict without plan state) start afresh.
        fresh = mode == _NEW
        is_init = flat.get("is_init", None)
        if is_init is not None:
            fresh |= is_init.reshape(rows, -1).any(-1).cpu()
        if fresh.any():
            self._restart(state, fresh)
        finished = finished_rows(flat)
        finished &= ~fresh
        mode = state["dorp_mode"].squeeze(-1)
        mode[finished & (mode != _FAILED)] = _DONE
        active = (mode != _FAILED) & (mode != _DONE)

        # Codes of the frames (and of the goals of new episodes): one encoder call.
        if active.any() or fresh.any():
            frames = torch.cat([pixels[active], goal_pixels[fresh]])
            codes = self._encode(frames)
            state["code"][active] = codes[: int(active.sum())]
            state["goal_code"][fresh] = codes[int(active.sum()) :]
        code, goal_code = state["code"], state["goal_code"]
        # The goal-image phase starts when every code is the goal's, and an open-loop goal
        # plan runs to its end even if frames on the way have other codes: otherwise the
        # two phases interrupt each other and the policy flips between them.
        goal_plan = self.goal_planner
        running = self._read_planner(flat, goal_plan, goal_plan.cursor_key) < self._read_planner(
            flat, goal_plan, goal_plan.length_key
        )
        relaxed = state["dorp_relaxed"].squeeze(-1)
        if self.reenter:
            self._track_reentry(state, active)
        at_goal = active & (
            (code == goal_code).all(-1)
            | ((mode == _GOAL) & running.squeeze(-1) & ~fresh)
            | (relaxed & ~fresh)
        )
        at_goal &= state["dorp_via"].squeeze(-1) < 0  # re-entering a code: not yet

        # Waypoint bookkeeping.
        mask = state["subgoal_mask"]
        # A hop that lands in the goal's codes counts as reached too (its edge is how the
        # group entered the goal code, which a stalled goal phase may re-enter).
        hop_reached = (
            active
            & ~fresh
            & (mode == _WAYPOINT)
            & ((code == state["subgoal_code"]) | ~mask).all(-1)
        )
        in_waypoint = active & ~at_goal & (mode == _WAYPOINT)
        reached = in_waypoint & hop_reached
        budget = state["dorp_budget"].squeeze(-1)
        out_of_budget = in_waypoint & ~reached & (budget <= 0)
        state["dorp_waypoints"][hop_reached] += 1
        state["dorp_restored"][hop_reached] = False
        state["dorp_entry_edge"][hop_reached] = state["dorp_edge"][hop_reached]
        if self.forget_blocked_edges:
            self._forget_blocked_edges(state, hop_reached)
        for row in out_of_budget.nonzero().squeeze(-1).tolist():
            self._remove_edge(state, row)
        need = active & ~at_goal & ((mode != _WAYPOINT) | reached | out_of_budget)
        need &= ~state["dorp_failed"].squeeze(-1)
        new_waypoint = torch.zeros(rows, dtype=torch.bool)
        for row in need.nonzero().squeeze(-1).tolist():
            new_waypoint[row] = self._next_waypoint(state, row)
        if self.goal_budget is not None:
            allowed = self.goal_budget * (1 + state["dorp_relaxed"].squeeze(-1).long())
            spent = active & at_goal & (state["dorp_goal_steps"].squeeze(-1) >= allowed)
            state["dorp_failed"][spent] = True
            state["dorp_end"][spent] = _GOAL_STALLED
            at_goal &= ~spent
        failed = state["dorp_failed"].squeeze(-1)
        mode[failed] = _FAILED

        # Modes, and fresh low-level plans where the target changed.
        entering_goal = at_goal & (mode != _GOAL)
        mode[at_goal] = _GOAL
        mode[new_waypoint] = _WAYPOINT
        state["dorp_mode"] = mode.unsqueeze(-1)
        planners = (
            (self.waypoint_planner, (mode == _WAYPOINT) & active & ~failed, new_waypoint),
            (self.goal_planner, (mode == _GOAL) & active, entering_goal),
        )
        action = torch.zeros(rows, 1, dtype=torch.int64)
        outputs: dict[str, torch.Tensor] = {}
        for planner, rows_mask, restart in planners:
            planner_state = {
                key: self._read_planner(flat, planner, key) for key in planner.state_keys
            }
            planner_state[planner.length_key][restart] = 0
            index = rows_mask.nonzero().squeeze(-1)
            if index.numel():
                sub = flat[index.to(flat.device)].clone(False)
                # The checked uint8 frames (float frames in [0, 1] converted once, here).
                sub.set(self.pixels_key, pixels[index].to(flat.device))
                sub.set(self.goal_pixels_key, goal_pixels[index].to(flat.device))
                for key in (
                    "code",
                    "goal_code",
                    "subgoal_code",
                    "subgoal_mask",
                    "goal_code_weight",
                ):
                    if key in state:
                        sub.set(key, state[key][index].to(flat.device))
                for key, value in planner_state.items():
                    sub.set(key, value[index].to(flat.device))
                if planner is self.waypoint_planner and self.action_prior_mix > 0:
                    sub.set(PRIOR_KEY, self._action_prior(state, index).to(flat.device))
                planner(sub)
                action[index] = sub.get(planner.action_key).reshape(-1, 1).cpu()
                for key in planner.state_keys:
                    planner_state[key][index] = sub.get(key).cpu().to(planner_state[key].dtype)
            outputs.update(planner_state)
        # A fresh waypoint plan in which no candidate reaches the waypoint is a miss; after
        # ``max_misses`` of them the edge is removed at once instead of when the budget
        # runs out (with the true dynamics a miss means the waypoint is out of reach).
        wp = self.waypoint_planner
        planned_now = (mode == _WAYPOINT) & (outputs[wp.cursor_key].squeeze(-1) == 1)
        missed = planned_now & (outputs[wp.plan_cost_key].squeeze(-1) >= self.miss_threshold)
        state["dorp_misses"][missed] += 1
        state["dorp_plans"][planned_now] += 1
        if self.replan_on_miss:
            # A plan that reaches the waypoint nowhere is not worth following: take its
            # first step only and plan again, instead of wandering for a whole horizon.
            outputs[wp.length_key][missed] = outputs[wp.cursor_key][missed]
        if self.max_misses is not None:
            gone = missed & (state["dorp_misses"].squeeze(-1) >= self.max_misses)
            state["dorp_budget"][gone] = 1  # 0 after the decrement below: removed next step
        state["dorp_budget"][mode == _WAYPOINT] -= 1
        state["dorp_waypoint_steps"][(mode == _WAYPOINT) & active] += 1
        in_goal = (mode == _GOAL) & active
        state["dorp_goal_steps"][in_goal] += 1
        if self.goal_patience is not None:
            self._watch_goal_progress(state, outputs, in_goal)

        if self.actions is not None:
            action = self.actions.from_index(action)
        out = {"action": action, **state, **outputs}
        for key, value in out.items():
            tensordict.set(key, value.reshape(*batch, *value.shape[1:]).to(tensordict.device))
        return tensordict

    # ------------------------------------------------------------------ #
    # Internals
    # ------------------------------------------------------------------ #
    def _restart(self, state: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        for key, value in state.items():
            value[rows] = _FILLS.get(key, 0)
        if self.goal_code_weight is not None:
            state["goal_code_weight"][rows] = self.goal_code_weight
        state["dorp_mode"][rows] = _NEW

    def _remove_edge(self, state: dict[str, torch.Tensor], row: int) -> None:
        """The current waypoint was not reached in time: remove its edge for this task."""
        edge = int(state["dorp_edge"][row])
        removed = state["dorp_removed"][row]
        count = int(state["dorp_replans"][row])
        if count >= self.max_removed_edges:
            state["dorp_failed"][row] = True
            state["dorp_end"][row] = _REMOVAL_LIMIT
            state["dorp_end_group"][row] = state["dorp_group"][row]
            return
        if self._reenter_hops and self._start_reentry(state, row, edge):
            state["dorp_replans"][row] += 1
            return
        if edge >= 0:
            free = (removed < 0).nonzero()
            removed[int(free[0]) if free.numel() else count % removed.shape[0]] = edge
        state["dorp_replans"][row] += 1

    def _start_reentry(self, state: dict[str, torch.Tensor], row: int, edge: int) -> bool:
        """Whether the failed hop ``edge`` gets a re-entry instead of being removed.

        Only when removing the edge would leave the group no path to its goal code, the
        group entered the hop's source code by a hop (``dorp_entry_edge``) and still sits
        in it or has drifted back to the code it came from, and this edge has not had
        its re-entry yet.
        """
        graph = self.graph
        entry = int(state["dorp_entry_edge"][row])
        if edge < 0 or entry < 0 or not self._may_reenter(state, row, edge):
            return False
        source = int(graph.edge_source[edge])
        if int(graph.indices[entry]) != source:
            return False  # entered some other node: the entry edge says nothing here
        group = int(graph.group_of_edge(edge))
        node = int(graph.node_of(state["code"][row], group))
        if node not in (source, int(graph.edge_source[entry])):
            return False  # drifted elsewhere than the hop's code or the one it came from
        target = int(graph.node_of(state["goal_code"][row], group))
        # Edges that failed once and wait for their re-entry are no way round either.
        doubtful = state["dorp_reentered"][row]
        without = torch.cat([state["dorp_removed"][row], doubtful, torch.tensor([edge])])
        if graph.next_waypoint(source, target, without)[0] >= 0:
            return False  # another path is left: removing the edge loses nothing
        state["dorp_via"][row] = source
        state["dorp_via_ban"][row] = entry
        state["dorp_via_left"][row] = node != source  # already back where it came from
        self._note_reentry(state, row, edge)
        return True

    def _start_goal_reentry(self, state: dict[str, torch.Tensor], row: int) -> bool:
        """Whether a stalled goal phase re-enters the goal code another way (before relaxing).

        The goal image may lie in another part of the goal code than the one the last hop
        entered (key-corridor: a code covering a room behind the door and part of another
        room). Only when the group of the last hop entered its goal node by that hop,
        another way into it exists, and this entry has not been re-entered already.
        """
        graph = self.graph
        entry = int(state["dorp_entry_edge"][row])
        if entry < 0 or int(state["dorp_via"][row]) >= 0:
            return False
        if not self._may_reenter(state, row, entry):
            return False
        if int(state["dorp_replans"][row]) >= self.max_removed_edges:
            return False
        node, source = int(graph.indices[entry]), int(graph.edge_source[entry])
        group = int(graph.group_of_edge(entry))
        if int(graph.node_of(state["code"][row], group)) != node:
            return False
        if int(graph.node_of(state["goal_code"][row], group)) != node:
            return False
        without = torch.cat([state["dorp_removed"][row], torch.tensor([entry])])
        if graph.next_waypoint(source, node, without)[0] < 0:
            return False  # no other way in
        state["dorp_via"][row] = node
        state["dorp_via_ban"][row] = entry
        state["dorp_via_left"][row] = False
        self._note_reentry(state, row, entry)
        state["dorp_replans"][row] += 1
        return True

    def _may_reenter(self, state: dict[str, torch.Tensor], row: int, edge: int) -> bool:
        """Whether ``edge`` has not had its re-entry yet and a slot is free for it."""
        slots = state["dorp_reentered"][row]
        return (
            self.max_reentries > 0 and not bool((slots == edge).any()) and bool((slots < 0).any())
        )

    def _note_reentry(self, state: dict[str, torch.Tensor], row: int, edge: int) -> None:
        slots = state["dorp_reentered"][row]
        slots[int((slots < 0).nonzero()[0])] = edge
        state["dorp_reentries"][row] += 1

    def _track_reentry(self, state: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        """Rows re-entering ``dorp_via``: note when they leave it, and end the re-entry
        when they are back in it after leaving."""
        via = state["dorp_via"].squeeze(-1)
        for row in (rows & (via >= 0)).nonzero().squeeze(-1).tolist():
            group = int(self.graph.group_of_edge(int(state["dorp_via_ban"][row])))
            node = int(self.graph.node_of(state["code"][row], group))
            if node != int(via[row]):
                state["dorp_via_left"][row] = True
            elif bool(state["dorp_via_left"][row]):
                state["dorp_via"][row] = -1
                state["dorp_via_ban"][row] = -1
                state["dorp_via_left"][row] = False

    def _reentry_waypoint(self, state: dict[str, torch.Tensor], row: int) -> bool:
        """Sets the next waypoint of a row that is re-entering ``dorp_via`` (if it still is).

        At ``dorp_via`` before leaving: back over the entry edge. Elsewhere: a shortest
        path back to ``dorp_via`` that does not use the entry edge. Back at ``dorp_via``
        after leaving, or with no such path: the re-entry ends and the usual path follows.
        """
        graph = self.graph
        via, ban = int(state["dorp_via"][row]), int(state["dorp_via_ban"][row])
        group = int(graph.group_of_edge(ban))
        node = int(graph.node_of(state["code"][row], group))
        removed = state["dorp_removed"][row]
        step = None  # dorp_via_left is kept by _track_reentry and _start_reentry
        if node == via and not bool(state["dorp_via_left"][row]):
            back = int(graph.edge_reverse[ban])
            if not bool(((removed == ban) | (removed == back)).any()):
                step = (int(graph.edge_source[ban]), back, 1)
        elif node != via and node >= 0:
            avoid = torch.cat([removed, torch.tensor([ban])])
            nxt, edge, distance = graph.next_waypoint(node, via, avoid)
            if nxt >= 0:
                step = (nxt, edge, distance)
        if step is None:
            state["dorp_via"][row] = -1
            state["dorp_via_ban"][row] = -1
            state["dorp_via_left"][row] = False
            return False
        self._set_waypoint(state, row, group, *step)
        return True

    def _forget_blocked_edges(self, state: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        """Rows whose group just reached a waypoint: restore the other groups' removed edges.

        A hop often fails because another object stands in the way; once a group has moved,
        that block may be gone, so edges removed for the other groups are free again. The
        count of removals (``dorp_replans``) is kept, so ``max_removed_edges`` still ends
        a task that keeps failing.
        """
        if not rows.any():
            return
        removed = state["dorp_removed"][rows]
        moved = state["dorp_group"][rows]
        other = (self.graph.group_of_edge(removed) != moved) & (removed >= 0)
        state["dorp_removed"][rows] = removed.masked_fill(other, -1)

    def _watch_goal_progress(
        self, state: dict[str, torch.Tensor], outputs: dict[str, torch.Tensor], rows: torch.Tensor
    ) -> None:
        """Drops the goal-code term of rows whose goal plans stopped getting cheaper."""
        gp = self.goal_planner
        planned = rows & (outputs[gp.cursor_key].squeeze(-1) == 1)
        cost = outputs[gp.plan_cost_key].squeeze(-1).float()
        best = state["dorp_goal_best"].squeeze(-1)
        better = planned & (cost < best - 1e-4 * best.abs().clamp(max=1e6))
        state["dorp_goal_best"][better] = cost[better].unsqueeze(-1)
        state["dorp_goal_stall"][better] = 0
        state["dorp_goal_stall"][rows & ~better] += 1
        relaxed = state["dorp_relaxed"].squeeze(-1)
        give_up = rows & ~relaxed & (state["dorp_goal_stall"].squeeze(-1) >= self.goal_patience)
        if self.reenter:
            for row in give_up.nonzero().squeeze(-1).tolist():
                if self._start_goal_reentry(state, row):
                    give_up[row] = False
                    state["dorp_goal_stall"][row] = 0
                    state["dorp_goal_best"][row] = float("inf")
        if give_up.any():
            state["dorp_relaxed"][give_up] = True
            state["goal_code_weight"][give_up] = 0.0
            state["dorp_goal_stall"][give_up] = 0
            state["dorp_goal_best"][give_up] = float("inf")
            outputs[gp.length_key][give_up] = 0  # replan without the term next step

    def _group_order(self, code: torch.Tensor, goal: torch.Tensor, current: int) -> list[int]:
        differing = [
            g
            for g, members in enumerate(self.graph.groups)
            if bool((code[members] != goal[members]).any())
        ]
        if isinstance(self.order, list):
            ranked = [g for g in self.order if g in differing]
        else:
            ranked = differing
        # Finish the group being moved before starting another (the authors' sequential
        # execution); "nearest" ranks the others by path length in _next_waypoint.
        if current in ranked:
            ranked.remove(current)
            ranked.insert(0, current)
        return ranked

    def _next_waypoint(self, state: dict[str, torch.Tensor], row: int) -> bool:
        """Sets the next waypoint of ``row``; marks the row failed when no group has a path."""
        if int(state["dorp_via"][row]) >= 0 and self._reentry_waypoint(state, row):
            return True
        code, goal = state["code"][row], state["goal_code"][row]
        removed = state["dorp_removed"][row]
        current = int(state["dorp_group"][row]) if int(state["dorp_mode"][row]) == _WAYPOINT else -1
        ranked = self._group_order(code, goal, current)
        best = self._best_hop(code, goal, removed, ranked, current)
        if (
            best is None
            and self.restore_when_stuck
            and not bool(state["dorp_restored"][row])
            and bool((removed >= 0).any())
        ):
            removed.fill_(-1)  # dorp_replans keeps counting towards max_removed_edges
            state["dorp_restored"][row] = True
            best = self._best_hop(code, goal, removed, ranked, current)
        if best is None:
            state["dorp_failed"][row] = True
            state["dorp_end"][row] = _NO_PATH
            state["dorp_end_group"][row] = ranked[0] if ranked else -1
            return False
        self._set_waypoint(state, row, *best)
        return True

    def _best_hop(
        self,
        code: torch.Tensor,
        goal: torch.Tensor,
        removed: torch.Tensor,
        ranked: list[int],
        current: int,
    ) -> tuple[int, int, int, int] | None:
        """``(group, next node, edge, distance)`` of the hop to take, ``None`` if no path."""
        graph = self.graph
        best: tuple[int, int, int, int] | None = None
        for group in ranked:
            node = int(graph.node_of(code, group))
            target = int(graph.node_of(goal, group))
            if node < 0 or target < 0:
                continue
            nxt, edge, distance = graph.next_waypoint(node, target, removed)
            if nxt < 0:
                continue
            if best is None or (
                self.order == "nearest" and distance < best[3] and group != current
            ):
                best = (group, nxt, edge, distance)
            if self.order != "nearest" or group == current:
                break
        return best

    def _set_waypoint(
        self,
        state: dict[str, torch.Tensor],
        row: int,
        group: int,
        nxt: int,
        edge: int,
        distance: int,
    ) -> None:
        """Makes node ``nxt`` of ``group`` (over ``edge``) the row's waypoint."""
        graph = self.graph
        code = state["code"][row]
        members = graph.groups[group]
        subgoal = code.clone()
        subgoal[members] = graph.node_code(nxt)
        state["subgoal_code"][row] = subgoal
        state["subgoal_mask"][row] = False
        state["subgoal_mask"][row, members] = True
        state["dorp_group"][row] = group
        state["dorp_edge"][row] = edge
        state["dorp_distance"][row] = distance
        state["dorp_budget"][row] = self.waypoint_budget
        state["dorp_misses"][row] = 0

    def _action_prior(self, state: dict[str, torch.Tensor], index: torch.Tensor) -> torch.Tensor:
        """``[len(index), A]``: the hop's one-hots' action shares, mixed with uniform draws."""
        hop = (state["subgoal_code"][index] != state["code"][index]) & state["subgoal_mask"][index]
        actions = self.waypoint_planner.num_actions
        weights = self.graph.action_weights(hop, actions)
        return self.action_prior_mix * weights + (1.0 - self.action_prior_mix) / actions

    def _encode(self, frames: torch.Tensor) -> torch.Tensor:
        module = self.encoder
        was_training = module.training
        module.eval()
        try:
            device = module_device(module)
            code = module(frames.to(device))[0]
        finally:
            module.train(was_training)
        if code.shape[-1] != self.num_onehots:
            raise ValueError(
                f"the encoder gave {code.shape[-1]} codes per frame, the graph has "
                f"{self.num_onehots} one-hots."
            )
        return code.to(torch.int64).cpu()

    def _frames(self, td: TensorDictBase, key: str) -> torch.Tensor:
        """The frames under ``key`` as uint8 ``[rows, C, H, W]`` on the CPU, checked once per
        call against the planning env (:func:`~dorp_rl.validation.check_task_frames`)."""
        value = td.get(key, None)
        if value is None:
            raise MissingKeyError(
                f"AbstractGoalPolicy needs {key!r} in the tensordict (uint8 [*B, C, H, W], or "
                "floats in [0, 1])."
            )
        env = self.waypoint_planner.env
        return check_task_frames(value, key, env, lead=tuple(td.batch_size)).cpu()

    def _read(self, td: TensorDictBase, key: str) -> torch.Tensor:
        rows = td.batch_size[0]
        c, r = self.num_onehots, max(1, self.max_removed_edges)
        shapes = {
            "code": c,
            "goal_code": c,
            "subgoal_code": c,
            "subgoal_mask": c,
            "dorp_removed": r,
            "dorp_reentered": max(1, self.max_reentries),
        }
        width = shapes.get(key, 1)
        dtype = (
            torch.bool
            if key in _BOOL_KEYS
            else torch.float32
            if key in _FLOAT_KEYS
            else torch.int64
        )
        value = td.get(key, None)
        if value is None:
            return torch.full((rows, width), _FILLS.get(key, 0), dtype=dtype)
        if tuple(value.shape) != (rows, width):
            raise ValueError(
                f"{key!r} must have shape [{rows}, {width}] for this policy, got "
                f"{list(value.shape)}; was it written by a policy with other codes?"
            )
        return value.cpu().to(dtype).clone()

    def _read_planner(self, td: TensorDictBase, planner: DiscreteMPCPlanner, key: str):
        rows = td.batch_size[0]
        value = td.get(key, None)
        if value is not None:
            return value.cpu().clone()
        if key == planner.plan_key:
            return torch.zeros(rows, planner.planning_horizon, dtype=torch.int64)
        dtype = torch.float32 if key == planner.plan_cost_key else torch.int64
        return torch.zeros(rows, 1, dtype=dtype)

    def extra_repr(self) -> str:
        return (
            f"order={self.order!r}, waypoint_budget={self.waypoint_budget}, "
            f"max_removed_edges={self.max_removed_edges}, goal_budget={self.goal_budget}"
        )


def make_waypoint_cost(
    encoder: nn.Module,
    *,
    waypoint_goal_weight: float = 0.0,
    step_penalty: float = 0.0,
    goal_blur_sigmas: Sequence[float] = (1.0, 2.0, 4.0),
    cache_size: int = 2**18,
) -> nn.Module:
    """The cost DORP's waypoint planner ranks its plans by (written under ``cost``).

    A :class:`~dorp_rl.planners.CodeMatchCost` on ``subgoal_code`` over the one-hots of
    ``subgoal_mask``; with ``waypoint_goal_weight > 0``, plus that weight times the goal
    image's blurred :class:`~dorp_rl.planners.PixelDistanceCost` (each folded over the
    plan's steps with ``min``), so that among plans reaching the waypoint those leaving
    the frame nearest the goal image win. ``step_penalty`` is the code term's cost per
    step of a matching frame (earlier arrival wins; see
    :class:`~dorp_rl.planners.CodeMatchCost`).

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.modules import OracleCodeEncoder
        >>> env = ObjectRearrangementEnv(num_objects=2)
        >>> cost = make_waypoint_cost(OracleCodeEncoder(env), waypoint_goal_weight=0.003)
        >>> type(cost).__name__
        'TensorDictSequential'
    """
    waypoint_goal_weight = check_float("waypoint_goal_weight", waypoint_goal_weight, low=0.0)
    alone = waypoint_goal_weight == 0
    code_cost = CodeMatchCost(
        encoder,
        "subgoal_code",
        onehots="subgoal_mask",
        out_key="cost" if alone else "waypoint_code_cost",
        step_penalty=step_penalty,
        cache_size=cache_size,
    )
    if alone:
        return code_cost
    return TensorDictSequential(
        code_cost,
        PixelDistanceCost(out_key="waypoint_pixel_cost", blur_sigmas=goal_blur_sigmas),
        WeightedCostSum(
            {"waypoint_code_cost": 1.0, "waypoint_pixel_cost": float(waypoint_goal_weight)},
            step_aggregation="min",
        ),
    )


def make_dorp_policy(
    env: EnvBase,
    encoder: nn.Module | str | Path,
    graph: CodeGraph | str | Path,
    *,
    low_level: str | EnvBase | nn.Module = "gt",
    planner: str = "rs",
    planning_horizon: int = 14,
    num_candidates: int = 1000,
    action_repeat: int = 1,
    action_persistence: float | None = None,
    goal_planner: str | None = None,
    order: str | Sequence[int] = "index",
    waypoint_budget: int = 28,
    max_removed_edges: int = 128,
    goal_budget: int | None = None,
    max_misses: int | None = 1,
    forget_blocked_edges: bool = True,
    restore_when_stuck: bool = True,
    reenter: bool | str | None = None,
    max_reentries: int = 8,
    replan_on_miss: bool | None = None,
    goal_code_weight: float = 100.0,
    goal_patience: int | None = 14,
    goal_blur_sigmas: Sequence[float] = (1.0, 2.0, 4.0, 8.0),
    waypoint_goal_weight: float | None = None,
    waypoint_step_penalty: float = 0.0,
    action_prior_mix: float | None = None,
    seed: int | None = None,
    **planner_kwargs: Any,
) -> AbstractGoalPolicy:
    """Assembles a DORP policy for ``env`` from checkpoints or objects.

    Args:
        env: the acting env (its dynamics serve as the oracle low level).
        encoder: an encoder, or the path of a representation checkpoint.
        graph: a :class:`~dorp_rl.planners.CodeGraph`, or the path of a saved one.
        low_level: ``"gt"`` (the env's true dynamics), a planning env
            (:class:`~dorp_rl.envs.WorldModelEnv`, ...), a video prediction model, or the
            path of a world-model checkpoint (:func:`~dorp_rl.policies.make_planning_env`).
        planner: ``"rs"`` (random shooting) or ``"cem"`` for the waypoint steps.
        planning_horizon, num_candidates, action_repeat: the low-level planners' shape.
        action_persistence: the random-shooting planners' probability that a sampled
            action repeats the one before it
            (:class:`~dorp_rl.planners.RandomShootingPlanner`). ``None`` (default): 0.5,
            so that plans pushing one object several cells the same way are common
            among the candidates (with uniform draws over many actions they are rare);
            0 draws uniformly, as the paper.
        goal_planner: the planner of the goal-image phase (default: as ``planner``).
        order, waypoint_budget, max_removed_edges, max_misses, forget_blocked_edges,
            restore_when_stuck, max_reentries: see :class:`AbstractGoalPolicy`.
        goal_budget: see :class:`AbstractGoalPolicy`; ``None`` (default): the goal-image
            phase is never given up before the env's step limit. A learned code may cover
            places far apart, so a block can hold its goal code many cells from its goal
            place; the pixel distance then needs more than a fixed budget to get it there.
        reenter, replan_on_miss: see :class:`AbstractGoalPolicy`; ``None`` (default):
            the ``dorp`` settings of the env's profile (:attr:`~dorp_rl.envs.EnvProfile.dorp`,
            else :data:`GENERIC_DORP_OPTIONS`): on in the key rooms, where learned codes
            often cover separate rooms and a plan that misses its waypoint only wanders;
            off in rearrangement, where hops fail because blocks stand in the way and
            following a missing plan moves them. ``reenter="goal"`` also re-enters from a
            goal phase stuck with two blocks in each other's goal places (docs/NOTES.md
            has the measurements of each choice).
        goal_code_weight: in the goal-image phase, the cost of a frame whose codes are
            not the goal's, added to its pixel distance (0: pixel distance alone, as the
            paper). Without it the pixel cost can pull objects out of their goal codes,
            and the policy flips between the two phases.
        goal_blur_sigmas: blurred terms of the goal-image pixel distance
            (:class:`~dorp_rl.planners.PixelDistanceCost`); ``()`` is the paper's plain
            L2, which is flat while a block does not overlap its goal place. The widest
            term (sigma 8 by default) still pulls a block from across a 16 x 16 frame.
        goal_patience: goal-phase steps without progress after which the goal-code
            term is dropped for the task (see :class:`AbstractGoalPolicy`).
        waypoint_goal_weight: weight of the goal image's pixel distance (the goal
            phase's blurred :class:`~dorp_rl.planners.PixelDistanceCost`) added to the
            waypoint cost. Kept small enough (at most 0.1 for a 16 x 16 frame at 0.003)
            that it never turns a plan that misses the waypoint into one that reaches it:
            it only ranks plans, so that of those reaching the waypoint the one whose
            frame is closest to the goal image wins, and a plan that misses moves objects
            towards their goal places instead of anywhere. ``None`` (default): the
            ``dorp`` settings of the env's profile (else 0, the code-match cost alone, as
            the paper): 0.003 in rearrangement, 0 in the key rooms, where pixel distance
            ignores the walls (docs/NOTES.md has the measurements).
        waypoint_step_penalty: the waypoint cost's cost per step of a frame at the
            waypoint (:func:`make_waypoint_cost`): earlier arrival wins; 0 (default)
            scores every step at the waypoint alike.
        action_prior_mix: share of the waypoint planner's actions drawn from those that
            changed the hop's one-hots in the play data (see :class:`AbstractGoalPolicy`).
            ``None`` (default): 0.8 when the graph has its play data's action counts
            (graphs built by :meth:`~dorp_rl.planners.CodeGraph.from_play_data`), else 0.
        seed: seeds the planners.
        **planner_kwargs: more arguments of the planners (e.g. ``optim_steps``, ``top_k``).

    Raises:
        ValueError: a graph built for another environment, encoder or code sizes, or an
            unknown planner or low level.
    """
    from dorp_rl.trainers import load_encoder

    seed = check_seed(seed, optional=True)
    goal_code_weight = check_float("goal_code_weight", goal_code_weight, low=0.0)
    waypoint_step_penalty = check_step_penalty(waypoint_step_penalty, "waypoint_step_penalty")
    waypoint_goal_weight = check_float(
        "waypoint_goal_weight", waypoint_goal_weight, low=0.0, optional=True
    )
    # The planners' own keywords, less those this function sets itself.
    passed_on = (
        set(keyword_names(RandomShootingPlanner)) | set(keyword_names(CategoricalCEMPlanner))
    ) - {"env", "cost", "execution", "key_prefix", "seed", "action_persistence"}
    passed_on -= {"planning_horizon", "num_candidates", "action_repeat"}
    check_keywords(planner_kwargs, passed_on, "make_dorp_policy (for its planners)")
    if not isinstance(env, EnvBase):
        raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
    identity = env_identity(env)
    profile = profile_of(env)
    suited = {**GENERIC_DORP_OPTIONS, **(profile.dorp if profile is not None else {})}
    reenter = suited["reenter"] if reenter is None else reenter
    replan_on_miss = suited["replan_on_miss"] if replan_on_miss is None else replan_on_miss
    if waypoint_goal_weight is None:
        waypoint_goal_weight = suited["waypoint_goal_weight"]
    if isinstance(encoder, (str, Path)):
        encoder = load_encoder(encoder, env)
    if isinstance(graph, (str, Path)):
        graph = CodeGraph.load(graph, encoder=encoder, env_config=identity)
    elif graph.env_config is not None and graph.env_config != identity:
        stored, wanted = graph.env_config, identity
        diff = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
        details = "; ".join(f"{k}: graph {stored.get(k)!r}, env {wanted.get(k)!r}" for k in diff)
        raise ValueError(
            f"the code graph was built from another environment's play data ({details})."
        )
    planning_env = make_planning_env(env, low_level)
    classes = {"rs": RandomShootingPlanner, "cem": CategoricalCEMPlanner}
    for name, value in (("planner", planner), ("goal_planner", goal_planner or planner)):
        if value not in classes:
            raise ValueError(f"{name} must be one of {sorted(classes)}, got {value!r}.")
    if action_persistence is not None and "rs" not in (planner, goal_planner or planner):
        raise ValueError(
            "action_persistence is a RandomShootingPlanner argument, but neither planner is "
            "random shooting: pass planner='rs' (or goal_planner='rs') or drop it."
        )
    rs_only = {"action_persistence": 0.5 if action_persistence is None else action_persistence}
    shape = {
        "planning_horizon": planning_horizon,
        "num_candidates": num_candidates,
        "action_repeat": action_repeat,
        "execution": "open_loop",
    }
    # Arguments only CEM has go to the CEM planners; anything else both planners take.
    cem_only = {k: v for k, v in planner_kwargs.items() if k in _CEM_ONLY}
    shared = {k: v for k, v in planner_kwargs.items() if k not in _CEM_ONLY}
    if cem_only and "cem" not in (planner, goal_planner or planner):
        raise ValueError(
            f"{sorted(cem_only)} are CategoricalCEMPlanner arguments, but neither planner is "
            "CEM: pass planner='cem' (or goal_planner='cem') or drop them."
        )
    waypoint_cost = make_waypoint_cost(
        encoder,
        waypoint_goal_weight=waypoint_goal_weight,
        step_penalty=waypoint_step_penalty,
        goal_blur_sigmas=goal_blur_sigmas,
    )
    if action_prior_mix is None:
        action_prior_mix = DEFAULT_ACTION_PRIOR_MIX if graph.action_counts is not None else 0.0
    action_prior_mix = check_float("action_prior_mix", action_prior_mix, low=0.0, high=1.0)
    waypoint = classes[planner](
        planning_env,
        waypoint_cost,
        **shape,
        seed=seed,
        key_prefix="waypoint_planner_",
        action_prior_key=PRIOR_KEY if action_prior_mix > 0 else None,
        **shared,
        **(cem_only if planner == "cem" else rs_only),
    )
    goal_kind = goal_planner or planner
    pixel_cost = PixelDistanceCost(out_key="pixel_cost", blur_sigmas=goal_blur_sigmas)
    goal_cost: nn.Module = pixel_cost
    if goal_code_weight > 0:
        # The goal-image phase starts with every code at the goal's: frames that leave
        # them cost more than any pixel distance, so the pixel cost cannot undo the plan.
        goal_cost = TensorDictSequential(
            pixel_cost,
            CodeMatchCost(encoder, "goal_code", out_key="goal_code_cost"),
            WeightedCostSum(
                {"pixel_cost": 1.0, "goal_code_cost": "goal_code_weight"},
                step_aggregation="min",
            ),
        )
    goal = classes[goal_kind](
        planning_env,
        goal_cost,
        **shape,
        seed=None if seed is None else derive_seed(seed, 1),
        key_prefix="goal_planner_",
        **shared,
        **(cem_only if goal_kind == "cem" else rs_only),
    )
    return AbstractGoalPolicy(
        encoder,
        graph,
        waypoint,
        goal,
        order=order,
        waypoint_budget=waypoint_budget,
        max_removed_edges=max_removed_edges,
        goal_budget=goal_budget,
        max_misses=max_misses,
        forget_blocked_edges=forget_blocked_edges,
        restore_when_stuck=restore_when_stuck,
        reenter=reenter,
        max_reentries=max_reentries,
        replan_on_miss=replan_on_miss,
        goal_code_weight=float(goal_code_weight) if goal_code_weight > 0 else None,
        goal_patience=goal_patience,
        action_prior_mix=action_prior_mix,
        actions=DiscreteActions.of(env),
    )
