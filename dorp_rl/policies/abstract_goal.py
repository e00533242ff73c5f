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
   left the task ends as failed (``dorp_failed``), never in an endless loop;
6. once every one-hot holds the goal's code, drive to the goal image with
   :class:`~dorp_rl.planners.PixelDistanceCost`; a task that spends more than
   ``goal_budget`` steps in this phase is given up too.

What the policy does where this loop fails (misses, blocked hops, codes covering two
places, a stalled goal phase) are its recovery rules (:mod:`dorp_rl.policies.recovery`),
each its own part with its own state keys, turned on by :class:`~dorp_rl.policies.DORPConfig`.
They return decisions (row masks, :class:`~dorp_rl.policies.recovery.Waypoints`,
:class:`~dorp_rl.policies.recovery.PlanDecision`) that the loop applies.

Every step runs on all rows at once: the loop and the rules act on bool masks over the
rows, and the graph answers every row's shortest-path question of a step in one search
(:meth:`~dorp_rl.planners.CodeGraph.next_waypoints`); no step loops over rows in Python.

All plan state lives in the tensordict (``[*B, ...]`` per env), declared once
(:func:`~dorp_rl.policies.state.loop_state_keys` lists the loop's keys, each rule its
own) and restarted on ``is_init``, so one instance serves a batch of envs with different
goals, partial resets and collector workers. Rows whose ``done`` is set, or that failed,
are not planned for (action 0).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import Compose, TensorDictPrimer

from dorp_rl.envs.spec import DiscreteActions
from dorp_rl.frames import check_task_frames
from dorp_rl.modules.encoder import eval_mode, module_device
from dorp_rl.planners.base import DiscreteMPCPlanner, finished_rows
from dorp_rl.planners.code_graph import CodeGraph
from dorp_rl.policies.action_priors import goal_action_prior, waypoint_action_prior
from dorp_rl.policies.checks import check_policy_parts
from dorp_rl.policies.config import DORPConfig
from dorp_rl.policies.records import task_records
from dorp_rl.policies.recovery import RecoveryRule, RuleContext, Waypoints, recovery_rules
from dorp_rl.policies.state import ENDINGS, MODES, PLANNER_INPUTS, PolicyState, loop_state_keys
from dorp_rl.validation import MissingKeyError, check_keywords, check_seed, derive_seed

if TYPE_CHECKING:  # pragma: no cover
    from dorp_rl.policies.recovery import PlanDecision

__all__ = ["LOOP_FIELDS", "AbstractGoalPolicy"]

_NEW, _WAYPOINT, _GOAL, _FAILED, _DONE = (MODES[m] for m in MODES)
_RUNNING, _NO_PATH, _GOAL_STALLED, _REMOVAL_LIMIT = (ENDINGS[e] for e in ENDINGS)
#: The :class:`~dorp_rl.policies.DORPConfig` fields the policy itself reads (the others
#: shape the planners :func:`~dorp_rl.policies.make_dorp_policy` gives it).
LOOP_FIELDS = (
    "order",
    "waypoint_budget",
    "max_removed_edges",
    "goal_budget",
    "max_misses",
    "miss_threshold",
    "replan_on_miss",
    "forget_blocked_edges",
    "restore_when_stuck",
    "reenter",
    "max_reentries",
    "avoid_noops",
    "noop_memory",
    "goal_code_weight",
    "goal_patience",
    "max_goal_returns",
    "action_prior_mix",
    "goal_action_prior_mix",
)


def _union(masks: Iterable[torch.Tensor | None]) -> torch.Tensor | None:
    """The rows of any of ``masks`` (``None`` entries left out; ``None`` if all are)."""
    out = None
    for mask in masks:
        if mask is not None:
            out = mask if out is None else out | mask
    return out


def _give_up(
    state: dict[str, torch.Tensor],
    rows: torch.Tensor,
    ending: int,
    group: torch.Tensor | None = None,
) -> None:
    """Marks ``rows`` as given up for ``ending`` (:data:`ENDINGS`), with the group left
    without a way on (``group`` ``[rows, 1]``; ``None``: leave ``dorp_end_group``)."""
    state["dorp_failed"][rows] = True
    state["dorp_end"][rows] = ending
    if group is not None:
        state["dorp_end_group"][rows] = group[rows]


class AbstractGoalPolicy(TensorDictModuleBase):
    """The DORP policy: code-graph waypoints for a low-level discrete MPC planner.

    See the module docstring for the loop and the keys it keeps.

    Args:
        encoder: maps frames to codes (``forward(pixels) -> (code, probs)`` and
            ``code_sizes``): a trained :class:`~dorp_rl.modules.DiscreteCodeEncoder`
            or an :class:`~dorp_rl.envs.OracleCodeEncoder`.
        graph: a :class:`~dorp_rl.planners.CodeGraph` built with that encoder.
        waypoint_planner: a :class:`~dorp_rl.planners.DiscreteMPCPlanner` whose cost
            reads ``subgoal_code`` and ``subgoal_mask`` (a
            :class:`~dorp_rl.planners.CodeMatchCost` with ``onehots="subgoal_mask"``).
        goal_planner: a planner whose cost reads ``goal_pixels`` (a
            :class:`~dorp_rl.planners.PixelDistanceCost`), with another ``key_prefix``;
            if its cost reads ``goal_code_weight``, the policy writes the goal-code
            term's weight there (:class:`~dorp_rl.policies.recovery.GoalRelaxation`).
        config: the settings (:class:`~dorp_rl.policies.DORPConfig`; the fields of
            :data:`LOOP_FIELDS` are read here); default: its defaults.
        rules: the recovery rules, in the order they are consulted (default: those
            ``config`` turns on, :func:`~dorp_rl.policies.recovery.recovery_rules`).
        actions: the acting env's action layout (the planners' indices are written in
            it: a one-hot env gets one-hot actions); ``None``: int64 indices ``[*B, 1]``.
        **overrides: fields of :data:`LOOP_FIELDS` changed from ``config``.

    Examples:
        >>> import torch
        >>> from dorp_rl.data import collect_play_data
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.envs import OracleCodeEncoder
        >>> from dorp_rl.planners import CodeGraph
        >>> from dorp_rl.policies import make_dorp_policy
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> oracle = OracleCodeEncoder(env)
        >>> graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
        >>> policy = make_dorp_policy(env, oracle, graph, num_candidates=200, seed=0)
        >>> td = env.rollout(100, policy, break_when_all_done=True, break_when_any_done=False)
        >>> bool(td["next", "success"].any(-2).all())
        True
        >>> [type(rule).__name__ for rule in policy.rules]
        ['MissedPlans', 'ForgetBlocked', 'RestoreWhenStuck', 'GoalRelaxation']
    """

    def __init__(
        self,
        encoder: nn.Module,
        graph: CodeGraph,
        waypoint_planner: DiscreteMPCPlanner,
        goal_planner: DiscreteMPCPlanner,
        config: DORPConfig | None = None,
        *,
        rules: Sequence[RecoveryRule] | None = None,
        actions: DiscreteActions | None = None,
        pixels_key: str = "pixels",
        goal_pixels_key: str = "goal_pixels",
        **overrides: Any,
    ) -> None:
        super().__init__()
        check_keywords(overrides, LOOP_FIELDS, "AbstractGoalPolicy")
        if config is not None and not isinstance(config, DORPConfig):
            raise ValueError(f"config must be a DORPConfig, got {type(config).__name__}.")
        config = (config or DORPConfig()).replace(**overrides)
        check_policy_parts(encoder, graph, waypoint_planner, goal_planner, config, goal_pixels_key)
        code_term = "goal_code_weight" in goal_planner.in_keys
        self.config = config
        self.encoder = encoder
        self.graph = graph
        self.waypoint_planner = waypoint_planner
        self.goal_planner = goal_planner
        self.order = config.order
        self.waypoint_budget = config.waypoint_budget
        self.max_removed_edges = config.max_removed_edges
        self.goal_budget = config.goal_budget
        self.action_prior_mix = float(config.action_prior_mix or 0.0)
        self.goal_action_prior_mix = float(config.goal_action_prior_mix or 0.0)
        self.actions = actions
        self.pixels_key = pixels_key
        self.goal_pixels_key = goal_pixels_key
        self.num_onehots = len(graph.code_sizes)
        # bool [G, C]: each group's one-hots; int64 [G]: each group's place in ``order``
        self._group_onehots = torch.zeros(graph.num_groups, self.num_onehots, dtype=torch.bool)
        for group, members in enumerate(graph.groups):
            self._group_onehots[group, members] = True
        self._group_rank = torch.arange(graph.num_groups)
        if not isinstance(config.order, str):
            self._group_rank[list(config.order)] = torch.arange(graph.num_groups)
        if rules is None:
            rules = recovery_rules(config, goal_code_term=code_term)
        self.rules = list(rules)
        for rule in self.rules:
            if not isinstance(rule, RecoveryRule):
                raise ValueError(f"rules must be RecoveryRule parts, got {type(rule).__name__}.")
            rule.bind(RuleContext(graph, waypoint_planner, goal_planner))
        loop_keys = loop_state_keys(self.num_onehots, self.max_removed_edges)
        self.state = PolicyState([*loop_keys, *(k for r in self.rules for k in r.state_keys())])
        if code_term and "goal_code_weight" not in self.state:
            raise ValueError(
                "the goal planner's cost reads 'goal_code_weight' but no rule writes it "
                "(GoalRelaxation does)."
            )
        planner_keys = [*waypoint_planner.in_keys, *goal_planner.in_keys]
        names = self.state.names()
        self.in_keys = list(
            dict.fromkeys([pixels_key, goal_pixels_key, *planner_keys, *names, "is_init", "done"])
        )
        self.out_keys = list(
            dict.fromkeys(
                ["action", *names, *waypoint_planner.state_keys, *goal_planner.state_keys]
            )
        )

    @property
    def state_keys(self) -> list[str]:
        """The names of the policy's state keys (loop and rules)."""
        return self.state.names()

    # ------------------------------------------------------------------ #
    # State declaration
    # ------------------------------------------------------------------ #
    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Declares the policy's own keys with their reset values.

        torchrl's collectors find this and the planners' primers when built with
        ``auto_register_policy_transforms=True``; :meth:`make_primer` gives all of them
        for ``env.append_transform``.
        """
        return self.state.primer()

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
        """How the policy fared on each task, from ``last`` (``[N]``, each task's last
        step): :func:`~dorp_rl.policies.records.task_records` of this policy's state."""
        return task_records(self.state, last)

    # ------------------------------------------------------------------ #
    # The loop
    # ------------------------------------------------------------------ #
    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One step of every row of ``tensordict``: the loop of the module docstring, in
        its order, each step a method below; writes ``action`` and the state."""
        batch = tensordict.batch_size
        flat = tensordict.reshape(-1) if len(batch) != 1 else tensordict
        frames = (self._frames(flat, self.pixels_key), self._frames(flat, self.goal_pixels_key))
        state = self.state.read(flat)
        fresh, active = self._start_rows(flat, state)
        self._encode_rows(state, frames, fresh, active)  # 1
        at_goal = self._goal_phase_rows(flat, state, fresh, active)  # 6: every code the goal's
        reached, missed = self._check_waypoints(state, fresh, active, at_goal)  # 5
        new_waypoint = self._choose_waypoints(state, active, at_goal, reached | missed)  # 2-4
        at_goal = self._spend_goal_budget(state, at_goal)  # 6: its step budget
        action, plans = self._act(flat, state, frames, active, at_goal, new_waypoint)
        if self.actions is not None:
            action = self.actions.from_index(action)
        out = {"action": action, **state, **plans[0], **plans[1]}
        for key, value in out.items():
            tensordict.set(key, value.reshape(*batch, *value.shape[1:]).to(tensordict.device))
        return tensordict

    def _start_rows(
        self, flat: TensorDictBase, state: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """New episodes (``is_init``, or a tensordict without plan state) start afresh;
        finished ones are done. Returns the ``fresh`` and the ``active`` rows."""
        rows = flat.batch_size[0]
        fresh = state["dorp_mode"].squeeze(-1) == _NEW
        is_init = flat.get("is_init", None)
        if is_init is not None:
            fresh |= is_init.reshape(rows, -1).any(-1).cpu()
        if fresh.any():
            self.state.restart(state, fresh)
        finished = finished_rows(flat) & ~fresh
        mode = state["dorp_mode"].squeeze(-1)
        mode[finished & (mode != _FAILED)] = _DONE
        return fresh, (mode != _FAILED) & (mode != _DONE)

    def _encode_rows(
        self,
        state: dict[str, torch.Tensor],
        frames: tuple[torch.Tensor, torch.Tensor],
        fresh: torch.Tensor,
        active: torch.Tensor,
    ) -> None:
        """1. Codes of the frames (and of the goals of new episodes): one encoder call."""
        pixels, goal_pixels = frames
        if active.any() or fresh.any():
            codes = self._encode(torch.cat([pixels[active], goal_pixels[fresh]]))
            state["code"][active] = codes[: int(active.sum())]
            state["goal_code"][fresh] = codes[int(active.sum()) :]
        for rule in self.rules:
            rule.track(state, active)
            rule.observe(state, pixels, active)

    def _goal_phase_rows(
        self,
        flat: TensorDictBase,
        state: dict[str, torch.Tensor],
        fresh: torch.Tensor,
        active: torch.Tensor,
    ) -> torch.Tensor:
        """6. The rows in the goal-image phase: every code is the goal's, or an open-loop
        goal plan is still running (even if frames on the way have other codes: otherwise
        the two phases interrupt each other and the policy flips between them)."""
        mode = state["dorp_mode"].squeeze(-1)
        gp = self.goal_planner
        running = self._read_planner(flat, gp, gp.cursor_key) < self._read_planner(
            flat, gp, gp.length_key
        )
        at_goal = (state["code"] == state["goal_code"]).all(-1) | (
            (mode == _GOAL) & running.squeeze(-1) & ~fresh
        )
        held = _union(rule.holds_goal(state, fresh) for rule in self.rules)
        if held is not None:
            at_goal |= held
        at_goal &= active
        delayed = _union(rule.delays_goal(state) for rule in self.rules)
        if delayed is not None:
            at_goal &= ~delayed
        return at_goal

    def _check_waypoints(
        self,
        state: dict[str, torch.Tensor],
        fresh: torch.Tensor,
        active: torch.Tensor,
        at_goal: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """5. Was each waypoint reached (a hop landing in the goal's codes counts too)?
        A waypoint not reached within its budget has its edge removed for the task.
        Returns the rows that ``reached`` their waypoint and those that ``missed`` it."""
        mode = state["dorp_mode"].squeeze(-1)
        hop_reached = (
            active
            & ~fresh
            & (mode == _WAYPOINT)
            & ((state["code"] == state["subgoal_code"]) | ~state["subgoal_mask"]).all(-1)
        )
        in_waypoint = active & ~at_goal & (mode == _WAYPOINT)
        reached = in_waypoint & hop_reached
        missed = in_waypoint & ~reached & (state["dorp_budget"].squeeze(-1) <= 0)
        state["dorp_waypoints"][hop_reached] += 1
        state["dorp_stale_removals"][hop_reached] = 0
        for rule in self.rules:
            rule.on_reached(state, hop_reached)
        self._remove_edges(state, missed)
        return reached, missed

    def _choose_waypoints(
        self,
        state: dict[str, torch.Tensor],
        active: torch.Tensor,
        at_goal: torch.Tensor,
        hop_over: torch.Tensor,
    ) -> torch.Tensor:
        """2-4. A group, its shortest path and the next waypoint, where one is needed (no
        waypoint yet, or the last one reached or missed); returns the rows given one."""
        mode = state["dorp_mode"].squeeze(-1)
        need = active & ~at_goal & ((mode != _WAYPOINT) | hop_over)
        need &= ~state["dorp_failed"].squeeze(-1)
        chosen = torch.zeros_like(need)
        for rule in self.rules:  # a rule's waypoint first (a re-entry under way)
            waypoints = rule.next_waypoints(state, need & ~chosen)
            if waypoints is not None:
                taken = need & ~chosen & (waypoints.node >= 0)
                self._set_waypoints(state, taken, waypoints)
                chosen |= taken
        left = need & ~chosen
        waypoints, first_group = self._shortest_hops(state, left)
        stuck = left & (waypoints.node < 0)
        retry = self._first_taken(stuck, lambda rule, rows: rule.when_stuck(state, rows))
        if retry.any():  # a rule changed the state (restored edges): search once more
            waypoints = waypoints.where(retry, self._shortest_hops(state, retry)[0])
        found = left & (waypoints.node >= 0)
        no_path = left & ~found
        _give_up(state, no_path, _NO_PATH, first_group.unsqueeze(-1))
        self._set_waypoints(state, found, waypoints)
        return chosen | found

    def _spend_goal_budget(
        self, state: dict[str, torch.Tensor], at_goal: torch.Tensor
    ) -> torch.Tensor:
        """6. A task past the goal phase's step budget is given up; returns the goal-phase
        rows left."""
        if self.goal_budget is not None:
            allowed = torch.full(at_goal.shape, self.goal_budget, dtype=torch.int64)
            scale = self._scale(state)
            if scale is not None:
                allowed = allowed * scale
            spent = at_goal & (state["dorp_goal_steps"].squeeze(-1) >= allowed)
            _give_up(state, spent, _GOAL_STALLED)
            at_goal = at_goal & ~spent
        return at_goal

    def _act(
        self,
        flat: TensorDictBase,
        state: dict[str, torch.Tensor],
        frames: tuple[torch.Tensor, torch.Tensor],
        active: torch.Tensor,
        at_goal: torch.Tensor,
        new_waypoint: torch.Tensor,
    ) -> tuple[torch.Tensor, tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]]:
        """4 and 6. The low level acts: the waypoint planner towards each row's waypoint,
        the goal planner towards the goal image (fresh plans where the target changed or
        a rule asks); then the step's counts and the rules that watch the plans. Returns
        the actions ``[rows, 1]`` (planner indices) and both planners' state."""
        mode = state["dorp_mode"].squeeze(-1)
        failed = state["dorp_failed"].squeeze(-1)
        mode[failed] = _FAILED
        entering_goal = at_goal & (mode != _GOAL)
        mode[at_goal] = _GOAL
        mode[new_waypoint] = _WAYPOINT
        state["dorp_mode"] = mode.unsqueeze(-1)
        wp, gp = self.waypoint_planner, self.goal_planner
        action = torch.zeros(mode.shape[0], 1, dtype=torch.int64)
        waypoint_rows = (mode == _WAYPOINT) & active & ~failed
        replan = _union(rule.forces_replan(state) for rule in self.rules)
        if replan is None:
            replan = torch.zeros(mode.shape[0], dtype=torch.bool)
        wp_state = self._plan(flat, state, frames, wp, waypoint_rows, new_waypoint | replan, action)
        gp_state = self._plan(
            flat, state, frames, gp, (mode == _GOAL) & active, entering_goal | replan, action
        )

        # The step's counts, then the rules that watch the plans.
        planned_now = (mode == _WAYPOINT) & (wp_state[wp.cursor_key].squeeze(-1) == 1)
        state["dorp_plans"][planned_now] += 1
        cost = wp_state[wp.plan_cost_key].squeeze(-1)
        for rule in self.rules:
            decision = rule.after_waypoint_plan(state, planned_now, cost)
            self._apply(decision, state, wp_state, gp_state)
        state["dorp_budget"][mode == _WAYPOINT] -= 1
        state["dorp_waypoint_steps"][(mode == _WAYPOINT) & active] += 1
        in_goal = (mode == _GOAL) & active
        state["dorp_goal_steps"][in_goal] += 1
        self._goal_stalls(state, wp_state, gp_state, in_goal)
        for rule in self.rules:
            rule.after_action(state, action, active & ~failed)
        return action, (wp_state, gp_state)

    # ------------------------------------------------------------------ #
    # Steps of the loop
    # ------------------------------------------------------------------ #
    def _scale(self, state: dict[str, torch.Tensor]) -> torch.Tensor | None:
        scales = [s for s in (r.goal_budget_scale(state) for r in self.rules) if s is not None]
        if not scales:
            return None
        out = scales[0]
        for scale in scales[1:]:
            out = out * scale
        return out

    def _plan(
        self,
        flat: TensorDictBase,
        state: dict[str, torch.Tensor],
        frames: tuple[torch.Tensor, torch.Tensor],
        planner: DiscreteMPCPlanner,
        rows_mask: torch.Tensor,
        restart: torch.Tensor,
        action: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """Runs ``planner`` on ``rows_mask`` (a fresh plan where ``restart``), writing its
        actions into ``action`` ``[rows, 1]``; returns its state ``{key: [rows, ...]}``."""
        planner_state = {key: self._read_planner(flat, planner, key) for key in planner.state_keys}
        planner_state[planner.length_key][restart] = 0
        index = rows_mask.nonzero().squeeze(-1)
        if index.numel():
            device = flat.device
            sub = flat[index.to(device)].clone(False)
            # The checked uint8 frames (float frames in [0, 1] converted once, here).
            sub.set(self.pixels_key, frames[0][index].to(device))
            sub.set(self.goal_pixels_key, frames[1][index].to(device))
            for key in PLANNER_INPUTS:
                if key in state:
                    sub.set(key, state[key][index].to(device))
            for key, value in planner_state.items():
                sub.set(key, value[index].to(device))
            if planner is self.waypoint_planner and self.action_prior_mix > 0:
                prior = waypoint_action_prior(
                    self.graph,
                    *(state[key][index] for key in ("code", "subgoal_code", "subgoal_mask")),
                    planner.num_actions,
                    self.action_prior_mix,
                )
                sub.set(planner.action_prior_key, prior.to(device))
            if planner is self.goal_planner and self.goal_action_prior_mix > 0:
                prior = goal_action_prior(
                    self.encoder,
                    self.graph,
                    frames[0][index],
                    frames[1][index],
                    planner.num_actions,
                    self.goal_action_prior_mix,
                )
                sub.set(planner.action_prior_key, prior.to(device))
            planner(sub)
            action[index] = sub.get(planner.action_key).reshape(-1, 1).cpu()
            for key in planner.state_keys:
                planner_state[key][index] = sub.get(key).cpu().to(planner_state[key].dtype)
        return planner_state

    def _apply(
        self,
        decision: PlanDecision | None,
        state: dict[str, torch.Tensor],
        wp_state: dict[str, torch.Tensor],
        gp_state: dict[str, torch.Tensor],
    ) -> None:
        """Carries out a rule's decision on the policy's and the planners' state."""
        if decision is None:
            return
        wp, gp = self.waypoint_planner, self.goal_planner
        if decision.cut is not None:  # the plan runs this step only
            wp_state[wp.length_key][decision.cut] = wp_state[wp.cursor_key][decision.cut]
        if decision.drop is not None:  # 0 after this step's decrement: removed next step
            state["dorp_budget"][decision.drop] = 1
        if decision.restart is not None:
            gp_state[gp.length_key][decision.restart] = 0

    def _goal_stalls(
        self,
        state: dict[str, torch.Tensor],
        wp_state: dict[str, torch.Tensor],
        gp_state: dict[str, torch.Tensor],
        rows: torch.Tensor,
    ) -> None:
        """Goal phases that stopped progressing: each stalled row is offered to the rules
        (a rule that takes it spends a removal), then the rule that found the stall acts
        on the rest."""
        gp = self.goal_planner
        planned = rows & (gp_state[gp.cursor_key].squeeze(-1) == 1)
        cost = gp_state[gp.plan_cost_key].squeeze(-1)
        for rule in self.rules:
            stalled = rule.goal_stalls(state, rows, planned, cost)
            if stalled is None:
                continue
            open_rows = stalled & ~self._removal_limit_reached(state)
            taken = self._first_taken(
                open_rows, lambda other, rows: other.on_goal_stall(state, rows)
            )
            self._count_removals(state, taken)
            decision = rule.after_goal_stalls(state, rows, stalled, taken)
            self._apply(decision, state, wp_state, gp_state)

    def _first_taken(
        self,
        rows: torch.Tensor,
        ask: Callable[[RecoveryRule, torch.Tensor], torch.Tensor | None],
    ) -> torch.Tensor:
        """Offers ``rows`` to the rules in turn (``ask(rule, rows left)``); each row goes to
        the first rule that takes it. Returns the rows taken."""
        taken = torch.zeros_like(rows)
        for rule in self.rules:
            left = rows & ~taken
            if not left.any():
                break
            took = ask(rule, left)
            if took is not None:
                taken |= took & left
        return taken

    def _remove_edges(self, state: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        """5. The waypoints of ``rows`` were not reached in time: remove their edges for the
        task (unless a rule handles the failed hop); past ``max_removed_edges`` since the
        last waypoint reached, give up."""
        limit = rows & self._removal_limit_reached(state)
        _give_up(state, limit, _REMOVAL_LIMIT, state["dorp_group"])
        rows = rows & ~limit
        handled = self._first_taken(rows, lambda rule, r: rule.instead_of_removal(state, r))
        edge = state["dorp_edge"].squeeze(-1)
        drop = (rows & ~handled & (edge >= 0)).nonzero().squeeze(-1)
        removed = state["dorp_removed"]
        free = removed < 0  # the first free slot, else the oldest by count
        slot = torch.where(
            free.any(-1),
            free.long().argmax(-1),
            state["dorp_replans"].squeeze(-1) % removed.shape[1],
        )
        removed[drop, slot[drop]] = edge[drop]
        self._count_removals(state, rows)

    def _removal_limit_reached(self, state: dict[str, torch.Tensor]) -> torch.Tensor:
        """Rows that removed ``max_removed_edges`` edges since they last reached a waypoint."""
        return state["dorp_stale_removals"].squeeze(-1) >= self.max_removed_edges

    @staticmethod
    def _count_removals(state: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        """Counts one more removal (or re-entry) of ``rows``, in all and since their last
        waypoint."""
        state["dorp_replans"][rows] += 1
        state["dorp_stale_removals"][rows] += 1

    def _shortest_hops(
        self, state: dict[str, torch.Tensor], rows: torch.Tensor
    ) -> tuple[Waypoints, torch.Tensor]:
        """2-3. For ``rows``, the group to move and the next hop on its shortest path:
        among the groups whose code differs from the goal's and that have a path left,
        the one being moved, else the first in ``order`` ("nearest": the shortest path,
        ties in index order). Returns the :class:`Waypoints` (node -1: no group has a
        path) and the first group in that order (-1: none differs), each ``[rows]``."""
        out = Waypoints.none(rows.shape[0])
        first = torch.full((rows.shape[0],), -1, dtype=torch.int64)
        index = rows.nonzero().squeeze(-1)
        n, groups = index.shape[0], self.graph.num_groups
        if not n:
            return out, first
        code, goal = state["code"][index], state["goal_code"][index]
        differing = ((code != goal).unsqueeze(1) & self._group_onehots).any(-1)  # [n, G]
        moving = state["dorp_mode"][index, 0] == _WAYPOINT
        current = torch.where(moving, state["dorp_group"][index, 0], -1)
        rank = self._group_rank.expand(n, groups).clone()
        rank[current.unsqueeze(-1) == torch.arange(groups)] = -1  # finish it first
        # the next hop of every differing group of every row, in one search
        group = torch.arange(groups).repeat(n)
        node = self.graph.nodes_of(code.repeat_interleave(groups, 0), group)
        target = self.graph.nodes_of(goal.repeat_interleave(groups, 0), group)
        ask = differing.reshape(-1) & (node >= 0) & (target >= 0)
        hop = Waypoints(group, *(torch.full_like(group, -1) for _ in range(3)))
        if ask.any():
            removed = state["dorp_removed"][index].repeat_interleave(groups, 0)[ask]
            found = self.graph.next_waypoints(node[ask], target[ask], removed)
            hop.node[ask], hop.edge[ask], hop.distance[ask] = found
        has_path = (hop.node >= 0).reshape(n, groups)
        score = rank
        if self.order == "nearest":  # the moving group first, then by distance
            score = torch.where(rank < 0, -1, hop.distance.reshape(n, groups) * (groups + 1) + rank)
        never = torch.iinfo(torch.int64).max
        best = torch.where(has_path, score, never).argmin(-1)
        pick = torch.arange(n) * groups + best
        chosen = has_path.any(-1)
        for mine, theirs in zip(out, hop, strict=True):
            mine[index[chosen]] = theirs[pick[chosen]]
        lead = torch.where(differing, rank, never).argmin(-1)
        first[index] = torch.where(differing.any(-1), lead, -1)
        return out, first

    def _set_waypoints(
        self, state: dict[str, torch.Tensor], rows: torch.Tensor, waypoints: Waypoints
    ) -> None:
        """4. Makes each row's ``waypoints.node`` (of its group, over its edge, its
        distance from the target) the waypoint of ``rows``, with a full budget."""
        index = rows.nonzero().squeeze(-1)
        if not index.numel():
            return
        codes, onehots = self.graph.node_codes(waypoints.node[index])
        state["subgoal_code"][index] = torch.where(onehots, codes, state["code"][index])
        state["subgoal_mask"][index] = onehots
        state["dorp_group"][index, 0] = waypoints.group[index]
        state["dorp_edge"][index, 0] = waypoints.edge[index]
        state["dorp_distance"][index, 0] = waypoints.distance[index]
        state["dorp_budget"][index] = self.waypoint_budget
        for rule in self.rules:
            rule.on_waypoint(state, rows)

    def _encode(self, frames: torch.Tensor) -> torch.Tensor:
        with eval_mode(self.encoder):
            code = self.encoder(frames.to(module_device(self.encoder)))[0]
        if code.shape[-1] != self.num_onehots:
            raise ValueError(
                f"the encoder gave {code.shape[-1]} codes per frame, the graph has "
                f"{self.num_onehots} one-hots."
            )
        return code.to(torch.int64).cpu()

    def _frames(self, td: TensorDictBase, key: str) -> torch.Tensor:
        """The frames under ``key`` as uint8 ``[rows, C, H, W]`` on the CPU, checked once per
        call against the planning env (:func:`~dorp_rl.frames.check_task_frames`)."""
        value = td.get(key, None)
        if value is None:
            raise MissingKeyError(
                f"AbstractGoalPolicy needs {key!r} in the tensordict (uint8 [*B, C, H, W], or "
                "floats in [0, 1])."
            )
        env = self.waypoint_planner.env
        return check_task_frames(value, key, env, lead=tuple(td.batch_size)).cpu()

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
        rules = ", ".join(type(rule).__name__ for rule in self.rules)
        return (
            f"order={self.order!r}, waypoint_budget={self.waypoint_budget}, "
            f"max_removed_edges={self.max_removed_edges}, goal_budget={self.goal_budget}, "
            f"rules=[{rules}]"
        )
