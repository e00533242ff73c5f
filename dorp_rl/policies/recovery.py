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
from typing import TYPE_CHECKING

import torch

from dorp_rl.envs.planning import row_hashes
from dorp_rl.policies.state import NOOPS_KEY, StateKey

if TYPE_CHECKING:  # pragma: no cover
    from dorp_rl.policies.abstract_goal import AbstractGoalPolicy
    from dorp_rl.policies.config import DORPConfig

__all__ = [
    "PlanDecision",
    "Waypoint",
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


#: A waypoint a rule chooses: ``(group, node, edge, distance)``, as the shortest path's.
Waypoint = tuple[int, int, int, int]


class RecoveryRule:
    """A part of the DORP policy; every hook does nothing unless a rule overrides it.

    ``state`` is the policy's state (``{key: [rows, width]}``, CPU), ``rows`` a bool mask
    ``[rows]`` and ``row`` one row index. A rule keeps its own keys of the state (its
    :meth:`state_keys`) and returns its decisions (masks, a waypoint, whether it takes a
    matter over), which the policy applies: no rule calls back into the policy or writes
    a planner's state. Hooks returning ``bool`` answer whether the rule took the matter
    over (the first rule that does wins).
    """

    policy: AbstractGoalPolicy

    def bind(self, policy: AbstractGoalPolicy) -> None:
        """Called once by the policy that owns the rule (its graph, its limits)."""
        self.policy = policy

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

    def instead_of_removal(self, state: State, row: int, edge: int) -> bool:
        """The hop over ``edge`` failed: handle it instead of removing the edge?"""
        return False

    def next_waypoint(self, state: State, row: int) -> Waypoint | None:
        """A waypoint for ``row`` instead of the shortest path's (``None``: the usual one)."""
        return None

    def when_stuck(self, state: State, row: int) -> bool:
        """No group has a path left: change the state so that the search is tried again?"""
        return False

    def on_waypoint(self, state: State, row: int) -> None:
        """A new waypoint was set for ``row``."""

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

    def on_goal_stall(self, state: State, row: int) -> bool:
        """The goal phase of ``row`` stopped progressing: take it over before it relaxes?
        A rule that does spends one of the task's removals (``max_removed_edges``), and
        is not asked once they are spent."""
        return False

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

    def on_waypoint(self, state: State, row: int) -> None:
        state["dorp_misses"][row] = 0

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
        other = (self.policy.graph.group_of_edge(removed) != moved) & (removed >= 0)
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

    def when_stuck(self, state: State, row: int) -> bool:
        removed = state["dorp_removed"][row]
        if bool(state["dorp_restored"][row]) or not bool((removed >= 0).any()):
            return False
        removed.fill_(-1)
        state["dorp_restored"][row] = True
        return True


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

    # -- bookkeeping
    def _may_reenter(self, state: State, row: int, edge: int) -> bool:
        slots = state["dorp_reentered"][row]
        return (
            self.max_reentries > 0 and not bool((slots == edge).any()) and bool((slots < 0).any())
        )

    def _note(self, state: State, row: int, edge: int) -> None:
        slots = state["dorp_reentered"][row]
        slots[int((slots < 0).nonzero()[0])] = edge
        state["dorp_reentries"][row] += 1

    def _end(self, state: State, row: int) -> None:
        state["dorp_via"][row] = -1
        state["dorp_via_ban"][row] = -1
        state["dorp_via_left"][row] = False

    # -- hooks
    def on_reached(self, state: State, rows: torch.Tensor) -> None:
        state["dorp_entry_edge"][rows] = state["dorp_edge"][rows]

    def track(self, state: State, active: torch.Tensor) -> None:
        """Rows re-entering ``dorp_via``: note when they leave it; back in it after
        leaving, the re-entry is over."""
        graph = self.policy.graph
        via = state["dorp_via"].squeeze(-1)
        for row in (active & (via >= 0)).nonzero().squeeze(-1).tolist():
            group = int(graph.group_of_edge(int(state["dorp_via_ban"][row])))
            node = int(graph.node_of(state["code"][row], group))
            if node != int(via[row]):
                state["dorp_via_left"][row] = True
            elif bool(state["dorp_via_left"][row]):
                self._end(state, row)

    def delays_goal(self, state: State) -> torch.Tensor:
        return state["dorp_via"].squeeze(-1) >= 0

    def instead_of_removal(self, state: State, row: int, edge: int) -> bool:
        """Only when removing ``edge`` leaves the group no path to its goal code, the group
        entered the hop's source code by a hop and still sits in it (or drifted back to
        the code it came from), and this edge has not had its re-entry yet."""
        if not self.hops:
            return False
        graph = self.policy.graph
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
        self._note(state, row, edge)
        return True

    def next_waypoint(self, state: State, row: int) -> Waypoint | None:
        """At ``dorp_via`` before leaving: back over the entry edge. Elsewhere: a shortest
        path back to ``dorp_via`` not over the entry edge. Back at ``dorp_via`` after
        leaving, or with no such path: the re-entry ends and the usual path follows."""
        via, ban = int(state["dorp_via"][row]), int(state["dorp_via_ban"][row])
        if via < 0:
            return None
        graph = self.policy.graph
        group = int(graph.group_of_edge(ban))
        node = int(graph.node_of(state["code"][row], group))
        removed = state["dorp_removed"][row]
        step = None
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
            self._end(state, row)
            return None
        return (group, *step)

    def on_goal_stall(self, state: State, row: int) -> bool:
        """Only when the group of the last hop entered its goal node by that hop, another
        way into it exists and this entry has not been re-entered already."""
        graph = self.policy.graph
        entry = int(state["dorp_entry_edge"][row])
        if entry < 0 or int(state["dorp_via"][row]) >= 0:
            return False
        if not self._may_reenter(state, row, entry):
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
        self._note(state, row, entry)
        return True


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

    def bind(self, policy: AbstractGoalPolicy) -> None:
        super().bind(policy)
        self.num_actions = policy.waypoint_planner.num_actions
        for planner in (policy.waypoint_planner, policy.goal_planner):
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
        # where each row's current frame is remembered ([rows, memory])
        found = (hashes == now) & seen.any(-1)
        for row in unchanged.nonzero().squeeze(-1).tolist():
            slots = found[row].nonzero().squeeze(-1)
            if slots.numel():
                slot = int(slots[0])
            else:  # a new frame to remember, in place of the oldest
                slot = int(ring[row, 0])
                ring[row, 0] = (slot + 1) % self.memory
                hashes[row, slot] = now[row, 0]
                seen[row, slot] = False
                found[row] = False
                found[row, slot] = True
            seen[row, slot, last[row, 0]] = True
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
