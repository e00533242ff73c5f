"""Recovery rules of the DORP policy: what it does when the paper's loop would fail.

The paper's loop (:class:`~dorp_rl.policies.AbstractGoalPolicy`) removes the edge of a
waypoint not reached within its budget, and gives the task up when no group has a path
left. Each rule here handles one way that loop fails, as its own part: it declares the
state keys it keeps (:class:`~dorp_rl.policies.state.StateKey`) and implements the hooks
of :class:`RecoveryRule` it needs; the policy calls the hooks of its rules in order at
fixed points of its loop and knows nothing else of them.

=====================  ===============================================================
rule                   what it does
=====================  ===============================================================
:class:`MissedPlans`   a fresh waypoint plan none of whose candidates reaches the
                       waypoint is a miss: after ``max_misses`` the edge goes at once;
                       ``replan_on_miss`` plans again after one step of such a plan
:class:`ForgetBlocked` a group reaching a waypoint frees the edges removed for the
                       other groups (an object that stood in the way has moved)
:class:`RestoreWhenStuck`  no path left but edges removed: restore them and try again
                       (once until a waypoint is reached)
:class:`Reentry`       a code covering two places: leave it over the edge it was entered
                       by and enter it another way, before removing the hop that fails
                       (or when the goal phase stalls in it)
:class:`GoalRelaxation`  the goal phase keeps the goal's codes (a weighted code term);
                       when its plans stop getting cheaper, the term is dropped
:class:`AvoidNoops`    an action that left the frame unchanged does not start a plan
                       again until the frame changes (a learned model may believe a
                       blocked move goes through, and plan it at every step)
=====================  ===============================================================

Settings come from :class:`~dorp_rl.policies.DORPConfig` (:func:`recovery_rules`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import torch

from dorp_rl.envs.planning import row_hashes
from dorp_rl.planners.base import DiscreteMPCPlanner
from dorp_rl.planners.code_graph import CodeGraph
from dorp_rl.policies.state import NOOPS_KEY, StateKey

if TYPE_CHECKING:  # pragma: no cover
    from dorp_rl.policies.config import DORPConfig

__all__ = [
    "PlanDecision",
    "RuleContext",
    "Waypoints",
    "AvoidNoops",
    "ForgetBlocked",
    "GoalRelaxation",
    "MissedPlans",
    "RecoveryRule",
    "Reentry",
    "RestoreWhenStuck",
    "recovery_rules",
]

State = dict[str, torch.Tensor]


@dataclass
class PlanDecision:
    """What a rule decides once the planners have run; the policy applies it.

    Attributes:
        cut: rows whose new waypoint plan runs for this step only (planned again next).
        drop: rows whose hop is given up next step (its edge removed, as when its budget
            runs out).
        restart: rows whose goal plan is made afresh next step.
    """

    cut: torch.Tensor | None = None
    drop: torch.Tensor | None = None
    restart: torch.Tensor | None = None


@dataclass(frozen=True)
class RuleContext:
    """The parts of its policy a rule may read (:meth:`RecoveryRule.bind`): the code graph
    and the two planners."""

    graph: CodeGraph
    waypoint_planner: DiscreteMPCPlanner
    goal_planner: DiscreteMPCPlanner


class Waypoints(NamedTuple):
    """Waypoints chosen for a batch of rows, each int64 ``[rows]``: the ``group`` moved,
    the ``node`` to reach (-1: none chosen for that row), the ``edge`` of the hop and the
    ``distance`` in hops to the group's goal code (as the shortest path's)."""

    group: torch.Tensor
    node: torch.Tensor
    edge: torch.Tensor
    distance: torch.Tensor

    @classmethod
    def none(cls, rows: int) -> Waypoints:
        """No waypoint for any of ``rows`` rows."""
        return cls(*(torch.full((rows,), -1, dtype=torch.int64) for _ in range(4)))

    def where(self, rows: torch.Tensor, other: Waypoints) -> Waypoints:
        """``other``'s waypoints on ``rows`` (bool ``[rows]``), these elsewhere."""
        return Waypoints(*(torch.where(rows, b, a) for a, b in zip(self, other, strict=True)))


class RecoveryRule:
    """A part of the DORP policy; every hook does nothing unless a rule overrides it.

    ``state`` is the policy's state (``{key: [rows, width]}``, CPU) and ``rows`` a bool
    mask ``[rows]``: every hook answers for a batch of rows at once. A rule keeps its own
    keys of the state (its :meth:`state_keys`) and returns its decisions (masks,
    waypoints, the rows whose matter it takes over), which the policy applies: no rule
    calls back into the policy or writes a planner's state. Of the rows offered to the
    rules in turn, each goes to the first rule that takes it.

    Examples:
        >>> import torch
        >>> from dorp_rl.policies.recovery import RecoveryRule
        >>> class GiveUpEarly(RecoveryRule):
        ...     "Spends no removal on a hop that fails: the task is given up instead."
        ...     def instead_of_removal(self, state, rows):
        ...         return rows
        >>> state = {"dorp_edge": torch.tensor([[3], [4]])}
        >>> GiveUpEarly().instead_of_removal(state, torch.tensor([True, False])).tolist()
        [True, False]
    """

    context: RuleContext

    def bind(self, context: RuleContext) -> None:
        """Called once by the policy that owns the rule, with the parts it may read."""
        self.context = context

    def state_keys(self) -> tuple[StateKey, ...]:
        """The keys the rule keeps in the policy's state."""
        return ()

    def track(self, state: State, active: torch.Tensor) -> None:
        """Each step, on the active rows, after the frames were encoded."""

    def observe(self, state: State, frames: torch.Tensor, active: torch.Tensor) -> None:
        """Each step, with the current frames uint8 ``[rows, C, H, W]``, before planning."""

    def forces_replan(self, state: State) -> torch.Tensor | None:
        """Rows whose planners must plan afresh this step (their plans went wrong)."""
        return None

    def after_action(self, state: State, action: torch.Tensor, rows: torch.Tensor) -> None:
        """Each step, with the chosen actions int64 ``[rows, 1]`` (planner indices) of the
        active ``rows``."""

    def holds_goal(self, state: State, fresh: torch.Tensor) -> torch.Tensor | None:
        """Rows that count as in the goal phase although their codes are not the goal's."""
        return None

    def delays_goal(self, state: State) -> torch.Tensor | None:
        """Rows that must not start the goal phase yet although their codes are the goal's."""
        return None

    def on_reached(self, state: State, rows: torch.Tensor) -> None:
        """``rows`` just reached their waypoint (its edge is still ``dorp_edge``)."""

    def instead_of_removal(self, state: State, rows: torch.Tensor) -> torch.Tensor | None:
        """The hops of ``rows`` (over their ``dorp_edge``) failed: the rows whose failure
        the rule handles instead of removing the edge (``None``: none)."""
        return None

    def next_waypoints(self, state: State, rows: torch.Tensor) -> Waypoints | None:
        """Waypoints for some of ``rows`` instead of the shortest path's (a row with
        ``node`` -1, or ``None`` for all: the usual one)."""
        return None

    def when_stuck(self, state: State, rows: torch.Tensor) -> torch.Tensor | None:
        """No group of ``rows`` has a path left: the rows whose state the rule changed so
        that the search is tried again (``None``: none)."""
        return None

    def on_waypoint(self, state: State, rows: torch.Tensor) -> None:
        """New waypoints were set for ``rows``."""

    def goal_budget_scale(self, state: State) -> torch.Tensor | None:
        """``[rows]`` factors of the goal phase's step budget."""
        return None

    def after_waypoint_plan(
        self, state: State, planned: torch.Tensor, cost: torch.Tensor
    ) -> PlanDecision | None:
        """``planned`` rows made a fresh waypoint plan of best cost ``cost`` ``[rows]``."""
        return None

    def goal_stalls(
        self, state: State, rows: torch.Tensor, planned: torch.Tensor, cost: torch.Tensor
    ) -> torch.Tensor | None:
        """``rows`` took a goal-phase step (``planned``: with a fresh plan of best cost
        ``cost``): the rows whose goal phase stopped progressing (``None``: none)."""
        return None

    def on_goal_stall(self, state: State, rows: torch.Tensor) -> torch.Tensor | None:
        """The goal phases of ``rows`` stopped progressing: the rows the rule takes over
        before they relax (``None``: none). Each row taken spends one of the task's
        removals (``max_removed_edges``); rows that spent them are not offered."""
        return None

    def after_goal_stalls(
        self, state: State, rows: torch.Tensor, stalled: torch.Tensor, taken: torch.Tensor
    ) -> PlanDecision | None:
        """After :meth:`goal_stalls`: of the ``stalled`` rows, ``taken`` were taken over by
        a rule; ``rows`` took a goal-phase step."""
        return None

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if k != "policy")
        return f"{type(self).__name__}({fields})"


class MissedPlans(RecoveryRule):
    """Waypoint plans that reach the waypoint nowhere (best cost >= ``threshold``).

    After ``max_misses`` of them in a row the edge is removed at once instead of when the
    budget runs out (``None``: only the budget counts); with ``replan_on_miss`` such a
    plan is followed for one step only, then the policy plans again.
    """

    def __init__(self, threshold: float, max_misses: int | None, replan_on_miss: bool) -> None:
        self.threshold = float(threshold)
        self.max_misses = max_misses
        self.replan_on_miss = bool(replan_on_miss)

    def state_keys(self) -> tuple[StateKey, ...]:
        return (StateKey("dorp_misses", doc="plans for this waypoint that reached it nowhere"),)

    def on_waypoint(self, state: State, rows: torch.Tensor) -> None:
        state["dorp_misses"][rows] = 0

    def after_waypoint_plan(
        self, state: State, planned: torch.Tensor, cost: torch.Tensor
    ) -> PlanDecision:
        missed = planned & (cost >= self.threshold)
        state["dorp_misses"][missed] += 1
        gone = None
        if self.max_misses is not None:
            gone = missed & (state["dorp_misses"].squeeze(-1) >= self.max_misses)
        return PlanDecision(cut=missed if self.replan_on_miss else None, drop=gone)


class ForgetBlocked(RecoveryRule):
    """A group that reaches a waypoint frees the edges removed for the other groups.

    Their hops may have failed only because an object stood in the way, which has now
    moved. The removals still count, so ``max_removed_edges`` still ends a task that
    keeps failing without reaching a waypoint.
    """

    def on_reached(self, state: State, rows: torch.Tensor) -> None:
        if not rows.any():
            return
        removed = state["dorp_removed"][rows]
        moved = state["dorp_group"][rows]
        other = (self.context.graph.group_of_edge(removed) != moved) & (removed >= 0)
        state["dorp_removed"][rows] = removed.masked_fill(other, -1)


class RestoreWhenStuck(RecoveryRule):
    """No group has a path left but edges were removed: restore them all and search again.

    Once until a waypoint is reached again, so a goal behind an edge that never works is
    still given up; the removals count towards ``max_removed_edges``.
    """

    def state_keys(self) -> tuple[StateKey, ...]:
        return (
            StateKey(
                "dorp_restored",
                torch.bool,
                doc="removed edges were restored since the last waypoint reached",
            ),
        )

    def on_reached(self, state: State, rows: torch.Tensor) -> None:
        state["dorp_restored"][rows] = False

    def when_stuck(self, state: State, rows: torch.Tensor) -> torch.Tensor:
        removed = state["dorp_removed"]
        restore = rows & ~state["dorp_restored"].squeeze(-1) & (removed >= 0).any(-1)
        removed[restore] = -1
        state["dorp_restored"][restore] = True
        return restore


class Reentry(RecoveryRule):
    """Re-enter a code another way: a learned code may cover two places (two rooms).

    When removing a failed hop would leave its group no path to the goal code, and the
    group entered the hop's code by a hop: go back out over that entry edge, re-enter the
    code another way and try the hop once more (``hops``). When the goal phase stalls in
    a goal code entered by a hop and another way in exists: the same, before the goal
    phase relaxes. Once per edge, at most ``max_reentries`` per task; each counts as a
    removal towards ``max_removed_edges``.
    """

    def __init__(self, max_reentries: int, hops: bool = True) -> None:
        self.max_reentries = int(max_reentries)
        self.hops = bool(hops)

    def state_keys(self) -> tuple[StateKey, ...]:
        return (
            StateKey("dorp_entry_edge", fill=-1, doc="edge of the last hop reached (-1: none)"),
            StateKey("dorp_via", fill=-1, doc="node being re-entered another way (-1: none)"),
            StateKey("dorp_via_ban", fill=-1, doc="the entry edge the re-entry must not use"),
            StateKey("dorp_via_left", torch.bool, doc="the group has left dorp_via on the way"),
            StateKey(
                "dorp_reentered",
                width=max(1, self.max_reentries),
                fill=-1,
                doc="edges re-entered for this task (-1: free slot)",
            ),
            StateKey("dorp_reentries", doc="re-entries started"),
        )

    # -- bookkeeping (``index``: int64 row indices)
    def _may_reenter(self, state: State, index: torch.Tensor, edge: torch.Tensor) -> torch.Tensor:
        """bool ``[len(index)]``: ``edge`` was not re-entered yet and a slot is free."""
        slots = state["dorp_reentered"][index]
        fresh = ~(slots == edge.unsqueeze(-1)).any(-1) & (slots < 0).any(-1)
        return fresh & (self.max_reentries > 0)

    def _note(self, state: State, index: torch.Tensor, edge: torch.Tensor) -> None:
        slots = state["dorp_reentered"][index]
        slots[torch.arange(index.shape[0]), (slots < 0).long().argmax(-1)] = edge
        state["dorp_reentered"][index] = slots
        state["dorp_reentries"][index] += 1

    def _start(
        self, state: State, index: torch.Tensor, via: torch.Tensor, ban: torch.Tensor
    ) -> None:
        state["dorp_via"][index, 0] = via
        state["dorp_via_ban"][index, 0] = ban

    def _end(self, state: State, index: torch.Tensor) -> None:
        state["dorp_via"][index] = -1
        state["dorp_via_ban"][index] = -1
        state["dorp_via_left"][index] = False

    def _has_path(
        self, nodes: torch.Tensor, goals: torch.Tensor, avoid: torch.Tensor, ask: torch.Tensor
    ) -> torch.Tensor:
        """bool ``[N]``: of the ``ask`` rows, those with a path from ``nodes`` to ``goals``
        that avoids the edges ``avoid`` ``[N, S]`` (False elsewhere)."""
        out = torch.zeros_like(ask)
        if ask.any():
            nxt = self.context.graph.next_waypoints(nodes[ask], goals[ask], avoid[ask])[0]
            out[ask] = nxt >= 0
        return out

    # -- hooks
    def on_reached(self, state: State, rows: torch.Tensor) -> None:
        state["dorp_entry_edge"][rows] = state["dorp_edge"][rows]

    def track(self, state: State, active: torch.Tensor) -> None:
        """Rows re-entering ``dorp_via``: note when they leave it; back in it after
        leaving, the re-entry is over."""
        graph = self.context.graph
        via = state["dorp_via"].squeeze(-1)
        index = (active & (via >= 0)).nonzero().squeeze(-1)
        if not index.numel():
            return
        group = graph.group_of_edge(state["dorp_via_ban"][index, 0])
        away = graph.nodes_of(state["code"][index], group) != via[index]
        was_away = state["dorp_via_left"][index, 0]
        state["dorp_via_left"][index[away]] = True
        self._end(state, index[~away & was_away])

    def delays_goal(self, state: State) -> torch.Tensor:
        return state["dorp_via"].squeeze(-1) >= 0

    def instead_of_removal(self, state: State, rows: torch.Tensor) -> torch.Tensor:
        """Only where removing the edge leaves the group no path to its goal code, the
        group entered the hop's source code by a hop and still sits in it (or drifted back
        to the code it came from), and this edge has not had its re-entry yet."""
        taken = torch.zeros_like(rows)
        index = rows.nonzero().squeeze(-1)
        if not self.hops or not index.numel():
            return taken
        graph = self.context.graph
        edge, entry = state["dorp_edge"][index, 0], state["dorp_entry_edge"][index, 0]
        ok = (edge >= 0) & (entry >= 0) & self._may_reenter(state, index, edge)
        source = graph.edge_source[edge.clamp(min=0)]
        entry_source = graph.edge_source[entry.clamp(min=0)]
        # entered the hop's code by the entry edge (else it says nothing here)
        ok &= graph.indices[entry.clamp(min=0)] == source
        group = torch.where(ok, graph.group_of_edge(edge), -1)
        node = graph.nodes_of(state["code"][index], group)
        ok &= (node == source) | (node == entry_source)  # not drifted elsewhere
        target = graph.nodes_of(state["goal_code"][index], group)
        # Edges that failed once and wait for their re-entry are no way round either.
        avoid = torch.cat(
            [state["dorp_removed"][index], state["dorp_reentered"][index], edge.unsqueeze(-1)], -1
        )
        ok &= ~self._has_path(source, target, avoid, ok)  # removing it loses the way
        self._start(state, index[ok], source[ok], entry[ok])
        state["dorp_via_left"][index[ok], 0] = node[ok] != source[ok]  # back where it came from
        self._note(state, index[ok], edge[ok])
        taken[index[ok]] = True
        return taken

    def next_waypoints(self, state: State, rows: torch.Tensor) -> Waypoints | None:
        """At ``dorp_via`` before leaving: back over the entry edge. Elsewhere: a shortest
        path back to ``dorp_via`` not over the entry edge. Back at ``dorp_via`` after
        leaving, or with no such path: the re-entry ends and the usual path follows."""
        via = state["dorp_via"].squeeze(-1)
        index = (rows & (via >= 0)).nonzero().squeeze(-1)
        if not index.numel():
            return None
        graph = self.context.graph
        ban = state["dorp_via_ban"][index, 0]
        group = graph.group_of_edge(ban)
        node = graph.nodes_of(state["code"][index], group)
        removed = state["dorp_removed"][index]
        target = via[index]
        step = Waypoints.none(index.shape[0])._replace(group=group)
        back = graph.edge_reverse[ban]
        open_back = ~((removed == ban.unsqueeze(-1)) | (removed == back.unsqueeze(-1))).any(-1)
        leave = (node == target) & ~state["dorp_via_left"][index, 0] & open_back
        step.node[leave] = graph.edge_source[ban[leave]]
        step.edge[leave] = back[leave]
        step.distance[leave] = 1
        way_in = (node != target) & (node >= 0)
        if way_in.any():
            avoid = torch.cat([removed, ban.unsqueeze(-1)], -1)[way_in]
            found = graph.next_waypoints(node[way_in], target[way_in], avoid)
            step.node[way_in], step.edge[way_in], step.distance[way_in] = found
        self._end(state, index[step.node < 0])
        out = Waypoints.none(rows.shape[0])
        for mine, theirs in zip(out, step, strict=True):
            mine[index] = theirs
        return out

    def on_goal_stall(self, state: State, rows: torch.Tensor) -> torch.Tensor:
        """Only where the group of the last hop entered its goal node by that hop, another
        way into it exists and this entry has not been re-entered already."""
        taken = torch.zeros_like(rows)
        index = rows.nonzero().squeeze(-1)
        if not index.numel():
            return taken
        graph = self.context.graph
        entry = state["dorp_entry_edge"][index, 0]
        ok = (entry >= 0) & (state["dorp_via"][index, 0] < 0)
        ok &= self._may_reenter(state, index, entry)
        node = graph.indices[entry.clamp(min=0)]
        source = graph.edge_source[entry.clamp(min=0)]
        group = torch.where(ok, graph.group_of_edge(entry), -1)
        ok &= graph.nodes_of(state["code"][index], group) == node
        ok &= graph.nodes_of(state["goal_code"][index], group) == node
        avoid = torch.cat([state["dorp_removed"][index], entry.unsqueeze(-1)], -1)
        ok = self._has_path(source, node, avoid, ok)  # another way in
        self._start(state, index[ok], node[ok], entry[ok])
        state["dorp_via_left"][index[ok]] = False
        self._note(state, index[ok], entry[ok])
        taken[index[ok]] = True
        return taken


class GoalRelaxation(RecoveryRule):
    """The goal phase's goal-code term, and dropping it when the goal plans stall.

    The goal planner's cost reads the term's weight per row from ``goal_code_weight``
    (``weight`` until relaxed, then 0). After ``patience`` goal-phase steps without a
    lower goal-plan cost the term is dropped (``None``: never), unless another rule takes
    the stall over; a relaxed task gets twice the goal phase's step budget. A relaxed
    goal phase that stalls again for ``patience`` steps while some code is no longer the
    goal's goes back to the code graph (the term restored), at most ``max_returns`` times
    per task: pixel distance alone can push an object out of its goal code into a place
    it cannot leave towards the goal, and waypoints lead it back into the goal code from
    another side. (Without the bound, codes covering places on both sides of a wall made
    tasks cycle between the two phases to the step limit.)
    """

    def __init__(self, weight: float, patience: int | None, max_returns: int = 0) -> None:
        self.weight = float(weight)
        self.patience = patience
        self.max_returns = int(max_returns)

    def state_keys(self) -> tuple[StateKey, ...]:
        return (
            StateKey(
                "dorp_goal_best",
                torch.float32,
                fill=float("inf"),
                doc="lowest goal-plan cost so far (inf: none)",
            ),
            StateKey("dorp_goal_stall", doc="goal-phase steps since that cost last fell"),
            StateKey("dorp_relaxed", torch.bool, doc="the goal phase dropped its code term"),
            StateKey("dorp_goal_returns", doc="relaxed goal phases sent back to the graph"),
            StateKey(
                "goal_code_weight",
                torch.float32,
                fill=self.weight,
                doc="weight of the goal-code term (read by the goal planner's cost)",
            ),
        )

    def holds_goal(self, state: State, fresh: torch.Tensor) -> torch.Tensor:
        return state["dorp_relaxed"].squeeze(-1) & ~fresh

    def goal_budget_scale(self, state: State) -> torch.Tensor:
        return 1 + state["dorp_relaxed"].squeeze(-1).long()

    def goal_stalls(
        self, state: State, rows: torch.Tensor, planned: torch.Tensor, cost: torch.Tensor
    ) -> torch.Tensor | None:
        if self.patience is None:
            return None
        cost = cost.float()
        best = state["dorp_goal_best"].squeeze(-1)
        better = planned & (cost < best - 1e-4 * best.abs().clamp(max=1e6))
        state["dorp_goal_best"][better] = cost[better].unsqueeze(-1)
        state["dorp_goal_stall"][better] = 0
        state["dorp_goal_stall"][rows & ~better] += 1
        relaxed = state["dorp_relaxed"].squeeze(-1)
        return rows & ~relaxed & (state["dorp_goal_stall"].squeeze(-1) >= self.patience)

    def after_goal_stalls(
        self, state: State, rows: torch.Tensor, stalled: torch.Tensor, taken: torch.Tensor
    ) -> PlanDecision | None:
        if self.patience is None:
            return None
        # a stall another rule took over: watch the goal phase afresh
        state["dorp_goal_stall"][taken] = 0
        state["dorp_goal_best"][taken] = float("inf")
        relaxed = state["dorp_relaxed"].squeeze(-1)  # a view: sees the rows relaxed below
        give_up = stalled & ~taken
        if give_up.any():  # replan without the term next step
            self._set_code_term(state, give_up, relaxed=True)
        off_goal = (state["code"] != state["goal_code"]).any(-1)
        back = rows & relaxed & off_goal & (state["dorp_goal_stall"].squeeze(-1) >= self.patience)
        back &= state["dorp_goal_returns"].squeeze(-1) < self.max_returns
        if back.any():  # leave the goal phase: the loop plans waypoints next step
            state["dorp_goal_returns"][back] += 1
            self._set_code_term(state, back, relaxed=False)
        return PlanDecision(restart=give_up | back)

    def _set_code_term(self, state: State, rows: torch.Tensor, *, relaxed: bool) -> None:
        """Drops (``relaxed``) or restores the goal-code term of ``rows``, restarting the
        stall watch (the policy restarts their goal plans)."""
        state["dorp_relaxed"][rows] = relaxed
        state["goal_code_weight"][rows] = 0.0 if relaxed else self.weight
        state["dorp_goal_stall"][rows] = 0
        state["dorp_goal_best"][rows] = float("inf")


class AvoidNoops(RecoveryRule):
    """An action that left a frame unchanged does not start a plan from that frame again.

    A learned model that believes a blocked move goes through (an object against a wall or
    another object) makes the planner choose it at every step, while the frame never
    changes, until the waypoint's budget runs out; and, when other moves change the frame
    in between, again each time the scene comes back. In a deterministic env the same
    action from the same frame changes nothing again, so the rule remembers, per row, the
    actions seen to change nothing at each of the last ``memory`` frames where one did
    (the oldest forgotten first), writes those of the current frame (bool ``[A]`` under
    :data:`NOOPS_KEY`), which the planners built with ``excluded_actions_key=NOOPS_KEY``
    do not start plans with, and has them plan afresh at a frame with remembered noops:
    after a step that changed nothing (an open-loop plan whose step changed nothing went
    wrong) and back at such a frame (the plan in hand may hold one). Frames are compared
    by a 64-bit hash of their pixels.

    Args:
        memory: frames remembered per row (1: only the current frame, forgotten as soon
            as the frame changes).
    """

    def __init__(self, memory: int = 32) -> None:
        if int(memory) < 1:
            raise ValueError(f"memory must be >= 1 (frames remembered), got {memory}.")
        self.memory = int(memory)
        self.num_actions = 0  # the planners' actions, set by bind

    def bind(self, context: RuleContext) -> None:
        super().bind(context)
        self.num_actions = context.waypoint_planner.num_actions
        for planner in (context.waypoint_planner, context.goal_planner):
            if planner.excluded_actions_key != NOOPS_KEY:
                raise ValueError(
                    f"AvoidNoops needs planners that read {NOOPS_KEY!r}: build them with "
                    f"excluded_actions_key={NOOPS_KEY!r} (make_dorp_policy does when "
                    "DORPConfig.avoid_noops is set)."
                )

    def state_keys(self) -> tuple[StateKey, ...]:
        return (
            StateKey(
                NOOPS_KEY,
                torch.bool,
                width=self.num_actions,
                doc="actions that left the current frame unchanged",
            ),
            StateKey("dorp_frame_hash", doc="hash of the last frame's pixels"),
            StateKey("dorp_last_action", fill=-1, doc="the last action (-1: none yet)"),
            StateKey(
                "dorp_noop_frames",
                width=self.memory,
                doc="hashes of the remembered frames where an action changed nothing",
            ),
            StateKey(
                "dorp_noop_actions",
                torch.bool,
                width=self.memory * self.num_actions,
                doc="per remembered frame (row-major), the actions that changed nothing",
            ),
            StateKey("dorp_noop_next", doc="the remembered frame written next (ring)"),
        )

    def frame_hash(self, frames: torch.Tensor) -> torch.Tensor:
        """int64 ``[rows, 1]``: the frame hash of each uint8 frame ``[rows, C, H, W]``
        (:func:`~dorp_rl.envs.planning.row_hashes`, the one the planners use)."""
        return row_hashes(frames).unsqueeze(-1)

    def observe(self, state: State, frames: torch.Tensor, active: torch.Tensor) -> None:
        if not active.any():
            return
        now = self.frame_hash(frames[active]).cpu()
        last = state["dorp_last_action"][active]
        unchanged = ((last >= 0) & (now == state["dorp_frame_hash"][active])).squeeze(-1)
        hashes = state["dorp_noop_frames"][active]
        seen = state["dorp_noop_actions"][active].unflatten(-1, (self.memory, -1))
        ring = state["dorp_noop_next"][active]
        # where each row's current frame is remembered ([rows, memory]): its first slot,
        # else (a new frame to remember) the oldest slot, written afresh
        found = (hashes == now) & seen.any(-1)
        known = found.any(-1)
        slot = torch.where(known, found.long().argmax(-1), ring[:, 0])
        new = (unchanged & ~known).nonzero().squeeze(-1)
        ring[new, 0] = (slot[new] + 1) % self.memory
        hashes[new, slot[new]] = now[new, 0]
        seen[new, slot[new]] = False
        found[new] = False
        found[new, slot[new]] = True
        noted = unchanged.nonzero().squeeze(-1)
        seen[noted, slot[noted], last[noted, 0]] = True
        current = (seen & found.unsqueeze(-1)).any(-2)
        state[NOOPS_KEY][active] = current
        state["dorp_noop_frames"][active] = hashes
        state["dorp_noop_actions"][active] = seen.flatten(-2)
        state["dorp_noop_next"][active] = ring
        state["dorp_frame_hash"][active] = now

    def forces_replan(self, state: State) -> torch.Tensor:
        # a plan whose action changed nothing went wrong, and a plan made elsewhere may
        # hold an action this frame is known to ignore: plan again without them
        return state[NOOPS_KEY].any(-1)

    def after_action(self, state: State, action: torch.Tensor, rows: torch.Tensor) -> None:
        state["dorp_last_action"][rows] = action[rows]


def recovery_rules(config: DORPConfig, *, goal_code_term: bool) -> list[RecoveryRule]:
    """The rules ``config`` turns on, in the order the policy consults them.

    ``goal_code_term``: the goal planner's cost reads ``goal_code_weight``
    (:class:`GoalRelaxation` writes it).
    """
    rules: list[RecoveryRule] = []
    rules.append(MissedPlans(config.miss_threshold, config.max_misses, config.replan_on_miss))
    if config.forget_blocked_edges:
        rules.append(ForgetBlocked())
    if config.restore_when_stuck:
        rules.append(RestoreWhenStuck())
    if config.reenter:
        rules.append(Reentry(config.max_reentries, hops=config.reenter is True))
    if config.avoid_noops:
        rules.append(AvoidNoops(config.noop_memory))
    if goal_code_term:
        rules.append(
            GoalRelaxation(config.goal_code_weight, config.goal_patience, config.max_goal_returns)
        )
    return rules
