"""AbstractGoalPolicy (DORP): solving tasks with oracle codes and the true dynamics, edge
removal, failure on unreachable goals, independent rows, collectors, and bad input."""

from __future__ import annotations

import functools

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector, MultiSyncCollector

from dorp_rl.data import collect_play_data
from dorp_rl.envs import KeyCorridorEnv, KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.planners import CodeGraph, CodeMatchCost, FirstArrival
from dorp_rl.policies import MODES, AbstractGoalPolicy, make_dorp_policy

SMALL = {"num_candidates": 200, "planning_horizon": 10}


@pytest.fixture(scope="module")
def two_objects():
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(4,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 20_000, seed=0), oracle)
    return env, oracle, graph


def fresh_batch(env, tasks):
    return env.reset(tasks.select("state", "goal_state").to(env.device), set_state=True)


def test_solves_two_object_tasks_with_oracle_codes(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    tasks = make_task_set(env, 4, seed=1)
    result = evaluate_policy(env, policy, tasks, tasks_per_rollout=4)
    assert result["success_rate"] == 1.0
    # Waypoints are followed one region at a time: well within the step limit.
    assert max(result["steps"]) < 6 * int(tasks["lower_bound"].max())


def test_removing_an_edge_changes_the_next_waypoint(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    td = policy(fresh_batch(env, make_task_set(env, 4, seed=2)))
    assert (td["dorp_mode"] == MODES["waypoint"]).all()
    old_subgoal, old_edge = td["subgoal_code"].clone(), td["dorp_edge"].clone()
    assert (old_edge >= 0).all() and (td["dorp_removed"] == -1).all()
    # Same frames, but row 1 ran out of budget: only row 1 removes its edge and replans.
    td["dorp_budget"][1] = 0
    td = policy(td)
    assert td["dorp_removed"][1, 0] == old_edge[1, 0] and td["dorp_replans"][1] == 1
    assert not torch.equal(td["subgoal_code"][1], old_subgoal[1])
    assert td["dorp_edge"][1] != old_edge[1]
    for row in (0, 2, 3):
        assert torch.equal(td["subgoal_code"][row], old_subgoal[row])
        assert (td["dorp_removed"][row] == -1).all() and td["dorp_replans"][row] == 0


def unreachable_goal_graph(env, oracle, goal_region: int, start_region: int):
    """The true graph without the goal's region, plus an edge the dynamics cannot follow."""
    buffer = collect_play_data(env, 4000, seed=0)
    codes = oracle.encode(buffer[:]["pixels"])
    next_codes = oracle.encode(buffer[:]["next", "pixels"])
    keep = (codes[:, 0] != goal_region) & (next_codes[:, 0] != goal_region)
    fake = torch.tensor([[start_region]])
    goal = torch.tensor([[goal_region]])
    return CodeGraph.from_transitions(
        torch.cat([codes[keep], fake]), torch.cat([next_codes[keep], goal]), oracle.code_sizes
    )


@pytest.mark.parametrize("restore", [False, True])
def test_unreachable_goal_ends_as_a_failure_within_the_budget(restore):
    """The only path is a fake edge: it fails, is removed and the task is given up. With
    ``restore_when_stuck`` the edge comes back once (no waypoint is reached in between),
    fails a second time and the task is given up then."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = unreachable_goal_graph(env, oracle, goal_region=15, start_region=0)
    policy = make_dorp_policy(
        env, oracle, graph, seed=0, waypoint_budget=5, restore_when_stuck=restore, **SMALL
    )
    tries = 2 if restore else 1
    planned_rows = []
    planning = policy.waypoint_planner.planning

    def counting(td, *args, **kwargs):
        planned_rows.append(td.batch_size[0])
        return planning(td, *args, **kwargs)

    policy.waypoint_planner.planning = counting
    start = torch.tensor([[[0, 0]]])
    goal = torch.tensor([[[14, 12]]])  # region 15; 26 moves away, and the edge is fake
    td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
    rollout = env.rollout(40, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    failed = rollout["dorp_failed"].squeeze(-1)[0]
    first = int(failed.float().argmax())
    assert failed.any() and first <= tries * (5 + 1)  # the budget, then the removal
    assert (rollout["dorp_mode"][0, first:] == MODES["failed"]).all()
    assert int(rollout["dorp_replans"][0, -1]) == tries
    # Without the rule the policy keeps no such key.
    restored = rollout.get("dorp_restored", None)
    assert (restored is not None and bool(restored[0, -1])) == restore
    # A failed task costs no more planning.
    assert len(planned_rows) == first


def test_goal_code_missing_from_the_graph_fails_at_once():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    # A graph over regions 0, 1 and 2 only: the goal's region 15 was never seen.
    graph = CodeGraph.from_transitions(
        torch.tensor([[0], [1]]), torch.tensor([[1], [2]]), oracle.code_sizes
    )
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    start = torch.tensor([[[0, 0]], [[0, 4]]])
    goal = torch.tensor([[[14, 12]], [[14, 12]]])
    td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
    td = policy(td)
    assert td["dorp_failed"].all() and (td["dorp_mode"] == MODES["failed"]).all()
    assert (td["action"] == 0).all()


def count_planned_rows(policy) -> list[int]:
    """Wraps both planners so that every planning call records how many rows it planned."""
    planned: list[int] = []
    for planner in (policy.waypoint_planner, policy.goal_planner):
        planning = planner.planning

        def counting(td, *args, _planning=planning, **kwargs):
            planned.append(td.batch_size[0])
            return _planning(td, *args, **kwargs)

        planner.planning = counting
    return planned


def test_a_stuck_goal_phase_is_given_up_after_its_budget():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=16)  # one code: the goal phase starts at once
    graph = CodeGraph.from_transitions(torch.tensor([[0]]), torch.tensor([[0]]), (1,))
    policy = make_dorp_policy(env, oracle, graph, seed=0, goal_budget=3, **SMALL)
    start, goal = torch.tensor([[[0, 0]]]), torch.tensor([[[14, 12]]])  # 26 moves away
    td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
    rollout = env.rollout(10, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    modes = rollout["dorp_mode"].squeeze(-1)[0].tolist()
    assert modes[:3] == [MODES["goal"]] * 3 and set(modes[3:]) == {MODES["failed"]}
    assert int(rollout["dorp_goal_steps"][0, -1]) == 3


def test_rows_with_different_goals_solve_independently(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    planned = count_planned_rows(policy)
    tasks = make_task_set(env, 4, seed=3)
    tasks["goal_state"][1] = tasks["goal_state"][0]  # two rows share a goal, two do not
    td = fresh_batch(env, tasks)
    rollout = env.rollout(
        400,
        policy,
        tensordict=td,
        auto_reset=False,
        break_when_any_done=False,
        break_when_all_done=True,
    )
    done = rollout["next", "done"].squeeze(-1)
    assert rollout["next", "success"].squeeze(-1)[done].all() and done.any(-1).all()
    # Finished rows cost no planning: at most one planned row per row and step until done.
    steps_until_done = done.float().argmax(-1) + 1
    assert len(set(steps_until_done.tolist())) > 1
    assert sum(planned) <= int(steps_until_done.sum()) < 4 * rollout.shape[1]


def test_runs_in_a_collector_and_restarts_on_new_episodes(two_objects):
    _, oracle, graph = two_objects
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=4, max_steps=30)
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    collector = Collector(
        env, policy, frames_per_batch=40, total_frames=80, auto_register_policy_transforms=True
    )
    batches = list(collector)
    collector.shutdown()
    data = torch.cat(batches, dim=-1)
    assert data["dorp_mode"].shape == (2, 40, 1)
    assert set(data["dorp_mode"].unique().tolist()) <= set(MODES.values())
    # Every new episode (solved, or cut at 30 steps) starts afresh with its own goal code.
    starts = data["is_init"].squeeze(-1)
    assert starts[:, 1:].any()
    assert torch.equal(data["goal_code"][starts], oracle.encode(data["goal_pixels"][starts]))
    assert (data["dorp_replans"][starts] == 0).all() and not data["dorp_failed"][starts].any()
    assert (data["dorp_mode"][starts] != MODES["done"]).all()


def _make_env(seed: int):
    return ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=seed, max_steps=20)


def _make_policy(graph_path: str):
    env = _make_env(0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    return make_dorp_policy(env, oracle, graph_path, seed=0, **SMALL)


def test_runs_in_a_multi_sync_collector_with_a_policy_factory(two_objects, tmp_path):
    _, _, graph = two_objects
    path = graph.save(tmp_path / "graph.pt")
    collector = MultiSyncCollector(
        [functools.partial(_make_env, 1), functools.partial(_make_env, 2)],
        policy_factory=functools.partial(_make_policy, str(path)),
        frames_per_batch=40,
        total_frames=40,
        auto_register_policy_transforms=True,
    )
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    assert batch.numel() == 40
    assert set(batch["dorp_mode"].unique().tolist()) <= {
        MODES["waypoint"],
        MODES["goal"],
        MODES["done"],
    }
    assert (batch["action"] >= 0).all() and (batch["action"] < 8).all()


def test_bad_input_gets_a_clear_error(two_objects, tmp_path):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    td = env.reset()
    td["goal_pixels"] = torch.zeros(4, 3, 8, 8, dtype=torch.uint8)
    with pytest.raises(ValueError, match="goal_pixels"):
        policy(td)
    td = env.reset()
    td["goal_pixels"] = td["goal_pixels"].float()
    with pytest.raises(ValueError, match="goal_pixels.*uint8"):
        policy(td)
    # An encoder with other code sizes than the graph's.
    other = DiscreteCodeEncoder(EncoderConfig.small((16, 16, 16)))
    with pytest.raises(ValueError, match=r"codes of sizes \(16, 16\), but .* \(16, 16, 16\)"):
        make_dorp_policy(env, other, graph, **SMALL)
    # A graph from another environment's play data.
    three = ObjectRearrangementEnv(num_objects=3, batch_size=(4,), seed=0)
    with pytest.raises(ValueError, match="another environment.*num_objects"):
        make_dorp_policy(three, OracleCodeEncoder(three), graph, **SMALL)
    path = graph.save(tmp_path / "graph.pt")
    with pytest.raises(ValueError, match="another environment"):
        make_dorp_policy(three, OracleCodeEncoder(three), path, **SMALL)
    with pytest.raises(ValueError, match="order"):
        make_dorp_policy(env, oracle, graph, order=[0, 0], **SMALL)
    with pytest.raises(ValueError, match="planner must be one of"):
        make_dorp_policy(env, oracle, graph, planner="mppi", **SMALL)
    with pytest.raises(ValueError, match="neither planner is CEM"):
        make_dorp_policy(env, oracle, graph, top_k=5, **SMALL)
    cem = make_dorp_policy(env, oracle, graph, planner="cem", top_k=5, optim_steps=2, **SMALL)
    assert (cem.waypoint_planner.top_k, cem.waypoint_planner.optim_steps) == (5, 2)
    assert type(cem.goal_planner).__name__ == "CategoricalCEMPlanner"
    with pytest.raises(ValueError, match="neither planner is random shooting"):
        make_dorp_policy(env, oracle, graph, planner="cem", action_persistence=0.3, **SMALL)
    with pytest.raises(ValueError, match="different key_prefix"):
        AbstractGoalPolicy(oracle, graph, policy.waypoint_planner, policy.waypoint_planner)


def test_a_waypoint_no_plan_reaches_is_removed_before_its_budget():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = unreachable_goal_graph(env, oracle, goal_region=15, start_region=0)
    start, goal = torch.tensor([[[0, 0]]]), torch.tensor([[[14, 12]]])
    first_failure = {}
    for misses in (None, 1):
        policy = make_dorp_policy(
            env,
            oracle,
            graph,
            seed=0,
            waypoint_budget=8,
            max_misses=misses,
            restore_when_stuck=False,
            **SMALL,
        )
        td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
        rollout = env.rollout(12, policy, tensordict=td, auto_reset=False)
        failed = rollout["dorp_failed"].squeeze(-1)[0]
        assert failed.any()
        first_failure[misses] = int(failed.float().argmax())
    # One plan without a candidate at the waypoint removes the edge the next step.
    assert first_failure[1] == 1 and first_failure[None] == 8


def _edge_of_group(graph, group):
    lo, hi = graph.node_offsets[group], graph.node_offsets[group + 1]
    return int(graph.indptr[lo]), int(graph.indptr[hi]) - 1


@pytest.mark.parametrize("forget", [True, False])
def test_reaching_a_waypoint_restores_the_other_groups_removed_edges(two_objects, forget):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, forget_blocked_edges=forget, **SMALL)
    td = policy(fresh_batch(env, make_task_set(env, 4, seed=2)))
    group = int(td["dorp_group"][0])
    other = 1 - group
    own_edge, other_edge = _edge_of_group(graph, group)[0], _edge_of_group(graph, other)[0]
    assert graph.group_of_edge(torch.tensor([own_edge, other_edge, -1])).tolist() == [
        group,
        other,
        -1,
    ]
    td["dorp_removed"][0, :2] = torch.tensor([own_edge, other_edge])
    # The frame is unchanged, so a waypoint equal to the current code counts as reached.
    td["subgoal_code"][0] = td["code"][0]
    td = policy(td)
    removed = set(td["dorp_removed"][0].tolist())
    assert own_edge in removed  # the moving group's failures stand
    assert (other_edge in removed) is not forget
    for row in (1, 2, 3):
        assert (td["dorp_removed"][row] == -1).all()


class DiagonalCodes(torch.nn.Module):
    """One object, two codes: quadrants top-left + bottom-right, and the other two.

    Each code covers two places that only meet at a corner, as a learned code can."""

    code_sizes = (2,)

    def __init__(self, env):
        super().__init__()
        self.oracle = OracleCodeEncoder(env, cell_size=8)  # quadrants 0 1 / 2 3

    def forward(self, pixels):
        quadrant = self.oracle(pixels)[0]
        code = (quadrant // 2 + quadrant % 2) % 2
        return code, torch.nn.functional.one_hot(code, 2).float()


@pytest.mark.parametrize("patience", [None, 5])
def test_a_goal_phase_that_stops_improving_drops_its_code_term(patience):
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    encoder = DiagonalCodes(env)
    graph = CodeGraph.from_transitions(torch.tensor([[0]]), torch.tensor([[1]]), (2,))
    policy = make_dorp_policy(
        env, encoder, graph, seed=0, goal_budget=40, goal_patience=patience, **SMALL
    )
    # Start and goal share code 0 but lie in opposite quadrants: keeping the code, no
    # plan gets closer; without it, pixel distance leads across the other code.
    start, goal = torch.tensor([[[2, 2]]]), torch.tensor([[[12, 12]]])
    td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
    rollout = env.rollout(90, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    solved = bool(rollout["next", "success"].any())
    relaxed = bool(rollout["dorp_relaxed"].any())
    weight = rollout["goal_code_weight"][0, :, 0]
    assert relaxed is (patience is not None)
    if patience is None:
        assert (weight == 100.0).all()
    else:
        assert solved
        first = int(rollout["dorp_relaxed"][0, :, 0].long().argmax())
        assert (weight[:first] == 100.0).all() and weight[first] == 0.0
        # Relaxed only after ``patience`` goal steps without a cheaper plan.
        assert int(rollout["dorp_goal_steps"][0, first]) >= patience


class QuadrantWorld:
    """One block, quadrant codes 0 1 / 2 3 and a graph 0-1, 0-2, 2-1, 1-3; ``at(q)`` shows
    the policy the block at ``cells[q]`` (after setting any state keys given). The hop
    1 -> 3 is a bridge, so its removal leaves no path: ``restore_when_stuck`` is off unless
    asked for, so that the tests see the removal and the task given up."""

    def __init__(self, reenter: bool, cells: dict, goal: list[int], **policy_kwargs):
        policy_kwargs.setdefault("restore_when_stuck", False)
        self.env = env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
        oracle = OracleCodeEncoder(env, cell_size=8)
        self.graph = CodeGraph.from_transitions(
            torch.tensor([[0], [0], [2], [1]]), torch.tensor([[1], [2], [1], [3]]), (4,)
        )
        self.policy = make_dorp_policy(
            env, oracle, self.graph, seed=0, reenter=reenter, **SMALL, **policy_kwargs
        )
        self.cells = cells
        self.td = env.reset(
            env.reset()
            .set("state", torch.tensor([[cells[0]]]))
            .set("goal_state", torch.tensor([[goal]])),
            set_state=True,
        )

    def at(self, quadrant, **overrides):
        self.td.set("pixels", self.env.render_state(torch.tensor([[self.cells[quadrant]]])))
        for key, value in overrides.items():
            self.td[key][0] = value
        return self.policy(self.td)

    def edge(self, a, b):
        node = self.graph.node_of
        return self.graph.edge_id(int(node(torch.tensor([a]), 0)), int(node(torch.tensor([b]), 0)))


@pytest.mark.parametrize("reenter", [True, False, "goal"])
def test_a_failed_bridge_hop_reenters_its_code_another_way_before_it_is_removed(reenter):
    """Quadrant codes 0 1 / 2 3 and a graph 0-1, 0-2, 2-1, 1-3: the hop 1 -> 3 is the
    only way to the goal. When it fails after entering 1 from 0, the group first leaves
    back to 0, comes into 1 through 2, and tries the hop again; a second failure removes it.
    With ``reenter="goal"`` (re-entry for a stalled goal phase only) it is removed at once.
    """
    world = QuadrantWorld(reenter, {0: [2, 2], 1: [2, 12], 2: [12, 2]}, goal=[12, 12])
    at, edge = world.at, world.edge

    assert int(at(0)["subgoal_code"][0, 0]) == 1
    assert int(at(1)["dorp_edge"][0]) == edge(1, 3)  # reached 1: now the bridge hop
    td = at(1, dorp_budget=0)  # the hop 1 -> 3 failed
    assert int(td["dorp_replans"][0]) == 1
    if reenter is not True:
        assert edge(1, 3) in td["dorp_removed"][0].tolist() and bool(td["dorp_failed"][0])
        return
    assert (td["dorp_removed"][0] == -1).all() and not bool(td["dorp_failed"][0])
    assert int(td["dorp_via"][0]) >= 0 and int(td["subgoal_code"][0, 0]) == 0  # back out
    assert int(td["dorp_edge"][0]) == edge(1, 0)
    assert int(at(0)["subgoal_code"][0, 0]) == 2  # into 1 again, not over 0 -> 1
    assert int(at(2)["subgoal_code"][0, 0]) == 1
    td = at(1)
    assert int(td["dorp_via"][0]) == -1 and int(td["dorp_edge"][0]) == edge(1, 3)
    td = at(1, dorp_budget=0)  # the same hop fails again: now it is removed
    assert edge(1, 3) in td["dorp_removed"][0].tolist() and bool(td["dorp_failed"][0])
    assert int(td["dorp_replans"][0]) == 2


def test_a_failed_hop_with_another_path_left_is_removed_without_reentry(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, reenter=True, **SMALL)
    td = policy(fresh_batch(env, make_task_set(env, 4, seed=2)))
    # As if each row had entered its code by a hop (from the waypoint's node).
    td["dorp_entry_edge"][:] = graph.edge_reverse[td["dorp_edge"]]
    old_edge = td["dorp_edge"].clone()
    td["dorp_budget"][:] = 0
    td = policy(td)
    assert (td["dorp_via"] == -1).all()
    assert (td["dorp_removed"][:, 0] == old_edge[:, 0]).all()


class SoftRegions(torch.nn.Module):
    """Oracle regions (cell 4) whose probabilities fall with the distance between regions,
    so that plans which miss a waypoint still prefer getting nearer to it."""

    code_sizes = (16,)

    def __init__(self, env):
        super().__init__()
        self.oracle = OracleCodeEncoder(env, cell_size=4)
        grid = torch.stack(torch.meshgrid(torch.arange(4), torch.arange(4), indexing="ij"), -1)
        self.register_buffer("centres", grid.reshape(16, 2))

    def forward(self, pixels):
        code = self.oracle(pixels)[0]
        here = self.centres[code[..., 0]]  # [*B, 2]
        distance = (here.unsqueeze(-2) - self.centres).abs().sum(-1).float()
        return code, (-distance).softmax(-1).unsqueeze(-2)


@pytest.mark.parametrize("replan", [True, False])
def test_a_plan_that_misses_its_waypoint_is_not_followed(replan):
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    encoder = SoftRegions(env)
    graph = unreachable_goal_graph(env, encoder.oracle, goal_region=15, start_region=0)
    policy = make_dorp_policy(
        env,
        encoder,
        graph,
        seed=0,
        waypoint_budget=8,
        max_misses=None,
        replan_on_miss=replan,
        **SMALL,
    )
    start, goal = torch.tensor([[[0, 0]]]), torch.tensor([[[14, 12]]])
    td = env.reset(env.reset().set("state", start).set("goal_state", goal), set_state=True)
    rollout = env.rollout(6, policy, tensordict=td, auto_reset=False)
    planner = policy.waypoint_planner
    cursor = rollout[planner.cursor_key][0, :, 0]
    length = rollout[planner.length_key][0, :, 0]
    # Every plan misses (the waypoint is 26 moves away) but the best ones head for it over
    # several steps; with replan_on_miss each is cut to its first step, so the policy
    # plans again at every step, otherwise it follows the plan.
    assert (rollout[planner.plan_cost_key] >= policy.config.miss_threshold).all()
    if replan:
        assert (cursor == 1).all() and (length == 1).all()
    else:
        assert (length > 1).any() and (cursor > 1).any()


@pytest.mark.parametrize("reenter", [True, False, "goal"])
def test_a_stalled_goal_phase_reenters_the_goal_code_another_way_first(reenter):
    """Quadrant codes and a graph 0-1, 0-2, 2-1, 1-3; the goal lies in quadrant 1, which
    the group entered from 0. When the goal phase stalls, the group leaves back to 0,
    comes into 1 through 2 and starts the goal phase again; without re-entry it relaxes."""
    world = QuadrantWorld(reenter, {0: [2, 2], 1: [2, 9], 2: [12, 2]}, goal=[2, 12])
    at, policy = world.at, world.policy

    assert int(at(0)["subgoal_code"][0, 0]) == 1
    assert int(at(1)["dorp_mode"][0]) == MODES["goal"]
    # The goal plans stop getting cheaper: the patience runs out on this step.
    td = at(
        1,
        dorp_goal_best=float("-inf"),
        dorp_goal_stall=policy.config.goal_patience - 1,
        **{policy.goal_planner.length_key: 0},
    )
    assert bool(td["dorp_relaxed"][0]) is not bool(reenter)
    if not reenter:
        return
    assert int(td["dorp_via"][0]) >= 0 and int(td["dorp_replans"][0]) == 1
    td = at(1)
    assert int(td["dorp_mode"][0]) == MODES["waypoint"] and int(td["subgoal_code"][0, 0]) == 0
    assert int(at(0)["subgoal_code"][0, 0]) == 2
    assert int(at(2)["subgoal_code"][0, 0]) == 1
    td = at(1)
    assert int(td["dorp_via"][0]) == -1 and int(td["dorp_mode"][0]) == MODES["goal"]
    assert not bool(td["dorp_relaxed"][0]) and not bool(td["dorp_failed"][0])


def test_a_relaxed_goal_phase_stalled_off_the_goal_codes_goes_back_to_the_graph():
    """Quadrant codes and a graph 0-1, 0-2, 2-1, 1-3; the goal lies in quadrant 1. The
    relaxed goal phase (pixel distance alone) pushed the block out into quadrant 0 and
    stalls there: with ``max_goal_returns=1`` the policy leaves the goal phase and plans
    the waypoint 1 again, with the code term back. Stalled inside the goal codes, or with
    the default 0, it stays relaxed."""
    cells, goal = {0: [2, 2], 1: [2, 9], 2: [12, 2]}, [2, 12]
    default = QuadrantWorld(False, cells, goal=goal)
    assert default.policy.config.max_goal_returns == 0
    world = QuadrantWorld(False, cells, goal=goal, max_goal_returns=1)
    at, policy = world.at, world.policy
    patience = policy.config.goal_patience
    stalled = {
        "dorp_goal_best": float("-inf"),
        "dorp_goal_stall": patience - 1,
        policy.goal_planner.length_key: 0,
    }
    default.at(0)
    default.at(1)
    default.at(1, **stalled)
    td = default.at(0, **stalled)
    assert bool(td["dorp_relaxed"][0]) and int(td["dorp_mode"][0]) == MODES["goal"]
    assert int(at(0)["subgoal_code"][0, 0]) == 1
    assert int(at(1)["dorp_mode"][0]) == MODES["goal"]
    td = at(1, **stalled)
    assert bool(td["dorp_relaxed"][0]) and float(td["goal_code_weight"][0]) == 0.0
    td = at(1, **stalled)  # stalled again, but every code is the goal's: still relaxed
    assert bool(td["dorp_relaxed"][0]) and int(td["dorp_mode"][0]) == MODES["goal"]
    td = at(0, **stalled)  # stalled again with the block out of its goal code
    assert int(td["dorp_mode"][0]) == MODES["goal"]  # this step was still a goal step
    assert not bool(td["dorp_relaxed"][0]) and float(td["goal_code_weight"][0]) == 100.0
    assert int(td[policy.goal_planner.length_key][0]) == 0
    td = at(0)
    assert int(td["dorp_mode"][0]) == MODES["waypoint"] and int(td["subgoal_code"][0, 0]) == 1
    assert not bool(td["dorp_failed"][0]) and int(td["dorp_goal_returns"][0]) == 1
    # Once per task (max_goal_returns=1): relaxed and stalled off the goal codes again,
    # it stays relaxed, so the two phases cannot take turns to the step limit.
    td = at(0, dorp_relaxed=True, goal_code_weight=0.0, **stalled)
    assert bool(td["dorp_relaxed"][0]) and int(td["dorp_mode"][0]) == MODES["goal"]
    assert int(td["dorp_goal_returns"][0]) == 1


def test_key_room_and_rearrangement_defaults(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    assert not policy.config.reenter and not policy.config.replan_on_miss
    # Random shooting draws runs of one action; a hop is removed after one missing plan.
    assert policy.waypoint_planner.action_persistence == 0.5
    assert policy.goal_planner.action_persistence == 0.5
    assert policy.config.max_misses == 1
    mixed = make_dorp_policy(
        env, oracle, graph, goal_planner="cem", action_persistence=0.0, **SMALL
    )
    assert mixed.waypoint_planner.action_persistence == 0.0
    assert type(mixed.goal_planner).__name__ == "CategoricalCEMPlanner"
    room = KeyCorridorEnv(batch_size=(1,), seed=0)
    room_oracle = OracleCodeEncoder(room, cell_size=4)
    room_graph = CodeGraph.from_play_data(collect_play_data(room, 500, seed=0), room_oracle)
    policy = make_dorp_policy(room, room_oracle, room_graph, seed=0, **SMALL)
    assert policy.config.reenter and policy.config.replan_on_miss
    # The goal image's pixel distance ranks waypoint plans in rearrangement only.
    assert "goal_pixels" not in policy.waypoint_planner.cost.in_keys
    rearrange = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    assert "goal_pixels" in rearrange.waypoint_planner.cost.in_keys
    policy = make_dorp_policy(room, room_oracle, room_graph, seed=0, reenter=False, **SMALL)
    assert not policy.config.reenter and policy.config.replan_on_miss
    with pytest.raises(ValueError, match="reenter must be True, False or 'goal'"):
        make_dorp_policy(room, room_oracle, room_graph, reenter="hops", **SMALL)


def test_the_goal_image_term_ranks_plans_that_reach_the_waypoint(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, waypoint_goal_weight=0.01, **SMALL)
    plain = make_dorp_policy(env, oracle, graph, seed=0, waypoint_goal_weight=0.0, **SMALL)
    # Block 0 must reach region (0, 1) (cells 0-3 x 4-7); block 1 keeps its region.
    start = torch.tensor([[0, 0], [12, 8]])
    goal = torch.tensor([[0, 6], [12, 8]])
    candidates = torch.stack(
        [
            torch.tensor([[0, 4], [12, 8]]),  # waypoint reached, 2 cells from the goal
            torch.tensor([[0, 5], [12, 8]]),  # waypoint reached, 1 cell from the goal
            torch.tensor([[0, 2], [12, 8]]),  # waypoint missed, 4 cells from the goal
        ]
    )
    render = env.render_state
    code = oracle.encode(render(goal[None]))[0]
    mask = torch.tensor([True, False])
    rollout = TensorDict(
        {
            "pixels": render(start[None]).expand(3, 1, 3, 16, 16),
            "goal_pixels": render(goal[None]).expand(3, 1, 3, 16, 16),
            "subgoal_code": code.expand(3, 1, 2),
            "subgoal_mask": mask.expand(3, 1, 2),
            ("next", "pixels"): render(candidates).unsqueeze(1),
        },
        batch_size=(3, 1),
    )
    with_goal = policy.waypoint_planner.cost(rollout.clone())
    score = with_goal.get(policy.waypoint_planner.cost_key)[:, 0]
    assert score[1] < score[0] < 0.5 <= score[2]  # closer wins; a miss stays a miss
    assert "goal_pixels" in policy.waypoint_planner.cost.in_keys
    without = plain.waypoint_planner.cost(rollout.clone())
    alone = without.get(plain.waypoint_planner.cost_key)[:, 0]
    assert abs(float(alone[1] - alone[0])) < 1e-2  # code match alone cannot tell them apart
    with pytest.raises(ValueError, match="waypoint_goal_weight"):
        make_dorp_policy(env, oracle, graph, waypoint_goal_weight=-1.0, **SMALL)


def test_waypoint_step_penalty_reaches_the_code_term(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, waypoint_step_penalty=2e-3, **SMALL)
    code_terms = [m for m in policy.waypoint_planner.cost.modules() if isinstance(m, CodeMatchCost)]
    assert [m.step_penalty for m in code_terms] == [2e-3]
    with pytest.raises(ValueError, match="step_penalty"):
        make_dorp_policy(env, oracle, graph, waypoint_step_penalty=0.5, **SMALL)


def replay_waypoint_plans(env, oracle, tasks, td):
    """Replays each row's waypoint plan from its task's start: (reaches [b], first
    arrival step [b], arrived at all [b])."""
    plan = td["waypoint_planner_plan"]
    reaches = td["waypoint_planner_cost"].squeeze(-1) < 0.5
    target, mask = td["subgoal_code"], td["subgoal_mask"]
    step = fresh_batch(env, tasks)
    arrived = torch.zeros(plan.shape, dtype=torch.bool)
    for t in range(plan.shape[-1]):
        step["action"] = plan[:, t : t + 1]
        step = env.step(step)["next"].clone()
        code = oracle.encode(step["pixels"])
        arrived[:, t] = ((code == target) | ~mask).all(-1)
    return reaches, arrived.float().argmax(-1), arrived.any(-1)


@pytest.mark.parametrize("prune", [False, True])
def test_first_arrival_plans_end_where_they_first_reach_the_waypoint(two_objects, prune):
    """With ``waypoint_first_arrival`` a waypoint plan is judged, and runs open loop, up
    to the first imagined step whose codes are the waypoint's: replayed in the env, the
    plan's last step is that first arrival, never a later one (pruned plans too)."""
    env, oracle, graph = two_objects
    policy = make_dorp_policy(
        env, oracle, graph, seed=0, waypoint_first_arrival=True, prune_plans=prune, **SMALL
    )
    assert any(isinstance(m, FirstArrival) for m in policy.waypoint_planner.cost.modules())
    assert policy.waypoint_planner.prune is policy.goal_planner.prune is prune
    plain = make_dorp_policy(env, oracle, graph, seed=0, waypoint_first_arrival=False, **SMALL)
    assert not any(isinstance(m, FirstArrival) for m in plain.waypoint_planner.cost.modules())
    tasks = make_task_set(env, 4, seed=2)
    td = policy(fresh_batch(env, tasks))
    length = td["waypoint_planner_length"].squeeze(-1)
    reaches, first, arrived = replay_waypoint_plans(env, oracle, tasks, td)
    assert reaches.any()
    assert torch.equal(length[reaches], first[reaches] + 1)
    assert arrived[reaches].all()


def test_pruned_waypoint_plans_are_never_longer(two_objects):
    """Pruning drops the detours of the same best candidates: every plan that reaches its
    waypoint is as short or shorter, and together they are shorter (few candidates: their
    best carries detours)."""
    env, oracle, graph = two_objects
    tasks = make_task_set(env, 4, seed=3)
    lengths = {}
    for prune in (False, True):
        policy = make_dorp_policy(
            env, oracle, graph, seed=0, prune_plans=prune, num_candidates=20, planning_horizon=10
        )
        td = policy(fresh_batch(env, tasks))
        reaches, _, _ = replay_waypoint_plans(env, oracle, tasks, td)
        assert reaches.all()
        lengths[prune] = td["waypoint_planner_length"].squeeze(-1)
    assert (lengths[True] <= lengths[False]).all()
    assert lengths[True].sum() < lengths[False].sum()


# ---------------------------------------------------------------- order, budgets, key rooms
def region(cell: list[int]) -> int:
    """The oracle's region (cell size 4) of a block's top-left cell."""
    return cell[0] // 4 * 4 + cell[1] // 4


def hops(a: list[int], b: list[int]) -> int:
    """Region hops between two cells: the graph of plentiful play links neighbours only."""
    return abs(a[0] // 4 - b[0] // 4) + abs(a[1] // 4 - b[1] // 4)


@pytest.mark.parametrize(
    ("order", "group"), [("index", 0), ("nearest", 1), ([1, 0], 1), ([0, 1], 0)]
)
def test_order_picks_the_group_to_move_first(two_objects, order, group):
    """Block 0 is 6 region hops from its goal, block 1 one hop: "index" (and [0, 1]) move
    block 0 first, "nearest" (and [1, 0]) the block with the shorter path."""
    env, oracle, graph = two_objects
    start, goal = [[0, 0], [8, 0]], [[12, 12], [8, 4]]
    policy = make_dorp_policy(env, oracle, graph, seed=0, order=order, **SMALL)
    td = env.reset(
        env.reset()
        .set("state", torch.tensor([start] * 4))
        .set("goal_state", torch.tensor([goal] * 4)),
        set_state=True,
    )
    td = policy(td)
    assert (td["dorp_group"] == group).all()
    assert (td["dorp_distance"] == hops(start[group], goal[group])).all()
    # The waypoint is the block's next region on its path; the other block keeps its code.
    waypoint = td["subgoal_code"][0].tolist()
    assert waypoint[1 - group] == region(start[1 - group])
    assert hops([waypoint[group] // 4 * 4, waypoint[group] % 4 * 4], start[group]) == 1
    assert td["subgoal_mask"][0].tolist() == [group == 0, group == 1]


def test_nearest_order_finishes_the_group_it_moves_and_solves_the_task(two_objects):
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, order="nearest", **SMALL)
    start, goal = [[0, 0], [8, 0]], [[12, 12], [8, 4]]
    td = env.reset(
        env.reset()
        .set("state", torch.tensor([start] * 4))
        .set("goal_state", torch.tensor([goal] * 4)),
        set_state=True,
    )
    rollout = env.rollout(
        80, policy, tensordict=td, auto_reset=False, break_when_any_done=False,
        break_when_all_done=True,
    )  # fmt: skip
    assert rollout["next", "success"].any(1).all()
    # Row 0's waypoints: block 1 (one hop) first, then block 0, never back.
    moving = rollout["dorp_mode"][0, :, 0] == MODES["waypoint"]
    groups = rollout["dorp_group"][0, :, 0][moving].tolist()
    assert groups[0] == 1 and groups == sorted(groups, reverse=True) and 0 in groups


@pytest.mark.parametrize("max_removed", [0, 2])
def test_max_removed_edges_ends_a_task_after_that_many_removals(two_objects, max_removed):
    """Each failed waypoint (budget spent) removes its edge; the failure after
    ``max_removed_edges`` removals ends the task instead."""
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, max_removed_edges=max_removed, **SMALL)
    td = policy(fresh_batch(env, make_task_set(env, 4, seed=2)))
    others = td["subgoal_code"][1:].clone()
    for failure in range(1, max_removed + 2):
        edge = int(td["dorp_edge"][0])
        td["dorp_budget"][0] = 0  # row 0 ran out of budget on the same frames
        td = policy(td)
        if failure <= max_removed:  # removed, and a new waypoint over another edge
            assert int(td["dorp_replans"][0]) == failure and not bool(td["dorp_failed"][0])
            assert edge in td["dorp_removed"][0].tolist() and int(td["dorp_edge"][0]) != edge
            assert int(td["dorp_mode"][0]) == MODES["waypoint"]
    assert bool(td["dorp_failed"][0]) and int(td["dorp_mode"][0]) == MODES["failed"]
    assert int(td["dorp_replans"][0]) == max_removed
    assert int(td["action"][0]) == 0  # a failed task is not planned for
    # The other rows kept their waypoints and removed nothing.
    assert torch.equal(td["subgoal_code"][1:], others)
    assert (td["dorp_replans"][1:] == 0).all() and not td["dorp_failed"][1:].any()


def test_reaching_a_waypoint_renews_the_removals_a_task_may_make(two_objects):
    """``max_removed_edges`` counts removals since the last waypoint reached: a task that
    keeps reaching waypoints is not given up for the removals on its way."""
    env, oracle, graph = two_objects
    policy = make_dorp_policy(env, oracle, graph, seed=0, max_removed_edges=2, **SMALL)
    td = policy(fresh_batch(env, make_task_set(env, 4, seed=2)))
    for _ in range(2):
        td["dorp_budget"][0] = 0
        td = policy(td)
    assert int(td["dorp_stale_removals"][0]) == 2 and not bool(td["dorp_failed"][0])
    # Row 0 reaches its waypoint: its frames already have the waypoint's code.
    td["subgoal_code"][0] = td["code"][0]
    waypoints = int(td["dorp_waypoints"][0])
    td = policy(td)
    assert int(td["dorp_waypoints"][0]) == waypoints + 1
    assert int(td["dorp_stale_removals"][0]) == 0 and int(td["dorp_replans"][0]) == 2
    for failure in (3, 4):  # two more removals are allowed ...
        td["dorp_budget"][0] = 0
        td = policy(td)
        assert int(td["dorp_replans"][0]) == failure and not bool(td["dorp_failed"][0])
    td["dorp_budget"][0] = 0  # ... and the next failure ends the task
    td = policy(td)
    assert bool(td["dorp_failed"][0]) and int(td["dorp_replans"][0]) == 4


@pytest.mark.parametrize("max_reentries", [0, 1, 8])
def test_max_reentries_caps_the_reentries_of_a_task(max_reentries):
    """The bridge world of the re-entry test: the hop 1 -> 3 fails and (with a re-entry
    left) the group backs out to 0 to come into 1 through 2; then the hop 0 -> 2 fails
    too. With 0 re-entries the first failure removes 1 -> 3 at once (no path is left,
    the task fails); with 1 the second failure is removed at once (the re-entry of 1
    ends, the group goes 0 -> 1 again); with more, it starts its own re-entry of 0."""
    cells = {0: [2, 2], 1: [2, 12], 2: [12, 2]}
    world = QuadrantWorld(True, cells, goal=[12, 12], max_reentries=max_reentries)
    assert world.policy.config.max_reentries == max_reentries
    at, edge = world.at, world.edge
    node = lambda q: int(world.graph.node_of(torch.tensor([q]), 0))  # noqa: E731

    assert int(at(0)["subgoal_code"][0, 0]) == 1
    assert int(at(1)["dorp_edge"][0]) == edge(1, 3)
    td = at(1, dorp_budget=0)  # the hop 1 -> 3 failed
    if max_reentries == 0:
        assert edge(1, 3) in td["dorp_removed"][0].tolist() and bool(td["dorp_failed"][0])
        return
    assert int(td["dorp_via"][0]) == node(1) and int(td["subgoal_code"][0, 0]) == 0
    assert td["dorp_reentered"][0].tolist().count(edge(1, 3)) == 1
    td = at(0)
    assert int(td["subgoal_code"][0, 0]) == 2 and int(td["dorp_edge"][0]) == edge(0, 2)
    td = at(0, dorp_budget=0)  # the hop 0 -> 2 on the way back in fails as well
    if max_reentries == 1:
        assert edge(0, 2) in td["dorp_removed"][0].tolist()
        assert int(td["dorp_via"][0]) == -1 and int(td["dorp_edge"][0]) == edge(0, 1)
    else:
        assert edge(0, 2) not in td["dorp_removed"][0].tolist()
        assert int(td["dorp_via"][0]) == node(0)
        assert edge(0, 2) in td["dorp_reentered"][0].tolist()
    assert not bool(td["dorp_failed"][0]) and int(td["dorp_replans"][0]) == 2


@pytest.mark.parametrize(
    ("room", "cell_size", "play_frames"), [(KeyWallEnv, 4, 8000), (KeyCorridorEnv, 2, 16_000)]
)
def test_solves_key_room_tasks_with_oracle_codes_and_the_true_dynamics(
    room, cell_size, play_frames
):
    """Oracle codes (the agent's region and the key bit, one graph group as in the paper's
    settings) and the true dynamics: every task solved, in at most 1.25x its lower bound
    (measured: exactly the lower bound). Key-corridor needs regions of 2 cells: regions of
    4 span walls, and 2 of 8 tasks failed."""
    env = room(batch_size=(8,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=cell_size)
    play = collect_play_data(room(batch_size=(8,), seed=1), play_frames, seed=0)
    graph = CodeGraph.from_play_data(play, oracle, ((0, 1),))
    policy = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    tasks = make_task_set(env, 8, seed=1)
    result = evaluate_policy(env, policy, tasks, tasks_per_rollout=8)
    assert result["success_rate"] == 1.0
    steps, bound = torch.tensor(result["steps"]), tasks["lower_bound"]
    assert (steps <= 1.25 * bound).all(), (steps.tolist(), bound.tolist())
    # Taking the key is part of every such task: the goal states hold it.
    assert (tasks["goal_state"][:, -1] == 1).all()
