"""Per-task records of an evaluation: how each task ended (solved, step limit, given up
with no path and for which group, goal phase stalled), the DORP policy's counts, the same
records from worker processes, the failure summary, tasks.csv and failures-first GIFs."""

from __future__ import annotations

import csv
import functools

import pytest
import torch
from tensordict import TensorDict

from dorp_rl.data import collect_play_data
from dorp_rl.envs import ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import (
    evaluate_parallel,
    evaluate_policy,
    failure_section,
    format_failures,
    make_task_set,
    summarize_failures,
    tasks_to_draw,
    write_task_records,
)
from dorp_rl.eval.results import pool_seeds
from dorp_rl.planners import CodeGraph
from dorp_rl.policies import make_dorp_policy

SMALL = {"num_candidates": 100, "planning_horizon": 8}


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def one_object_tasks(starts, goals) -> TensorDict:
    """Tasks of the 1-object env from (row, col) starts and goals, with Manhattan bounds."""
    state = torch.tensor([[s] for s in starts])
    goal = torch.tensor([[g] for g in goals])
    bound = (state - goal).abs().sum((-1, -2))
    return TensorDict(state=state, goal_state=goal, lower_bound=bound, batch_size=[len(starts)])


def make_policy(env, graph=None, **kwargs):
    oracle = OracleCodeEncoder(env, cell_size=4)
    if graph is None:
        graph = CodeGraph.from_play_data(collect_play_data(env, 3000, seed=0), oracle)
    return make_dorp_policy(env, oracle, graph, seed=0, **{**SMALL, **kwargs})


def test_records_say_solved_no_path_for_its_group_and_step_limit() -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(3,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    # Regions 0 -> 1 -> 2 only: a goal in region 15 has no path; one in region 1 has.
    graph = CodeGraph.from_transitions(
        torch.tensor([[0], [1]]), torch.tensor([[1], [2]]), oracle.code_sizes
    )
    policy = make_policy(env, graph)
    # Task 0: next region, 2 moves; task 1: goal region never seen; task 2: two regions
    # away (8 moves) with 3 steps allowed.
    tasks = one_object_tasks([(0, 2), (0, 0), (0, 0)], [(0, 4), (14, 12), (0, 9)])
    result = evaluate_policy(env, policy, tasks, max_steps=3, tasks_per_rollout=3, seed=0)
    records = result["records"]
    assert [r["task"] for r in records] == [0, 1, 2]
    assert [r["outcome"] for r in records] == ["solved", "no_path", "step_limit"]
    assert [r["steps"] for r in records] == result["steps"] == [2, 3, 3]
    assert records[1]["group"] == 0 and records[1]["phase"] == "failed"
    assert records[1]["plans"] == 0 and records[1]["waypoint_steps"] == 0
    assert records[0]["group"] is None and records[2]["group"] is None
    # Task 2 spent all of its 3 steps moving towards its first waypoint (4 moves away).
    assert records[2]["phase"] == "waypoint" and records[2]["waypoint_steps"] == 3
    assert records[2]["plans"] >= 1 and records[2]["edge_removals"] == 0
    summary = summarize_failures(records)
    assert summary["failed"] == [1, 2]
    assert summary["outcomes"] == {"no_path": 1, "step_limit": 1}
    assert summary["groups"] == {"no_path": {0: 1}}
    text = format_failures(records, "dorp")
    assert text.startswith("dorp: 1 of 3 solved; 2 failed: ")
    assert "no_path 1 (group 0: 1)" in text and "failed tasks: 1, 2" in text
    assert tasks_to_draw(records, 2) == [1, 2] and tasks_to_draw(records, 5) == [1, 2, 0]


def test_a_goal_phase_out_of_budget_is_recorded_as_goal_stalled() -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    # Start and goal in one 4x4 region: the goal phase starts at once, and with one step
    # of budget (goal_patience None: never relaxed) it cannot move the block 3 cells.
    policy = make_policy(env, goal_budget=1, goal_patience=None)
    tasks = one_object_tasks([(0, 0)], [(3, 0)])
    result = evaluate_policy(env, policy, tasks, max_steps=10, tasks_per_rollout=1, seed=0)
    (record,) = result["records"]
    assert record["outcome"] == "goal_stalled" and record["steps"] == 10
    assert record["goal_steps"] == 1 and record["waypoint_steps"] == 0
    assert record["waypoints"] == 0 and record["relaxed"] == 0


@pytest.mark.parametrize("restore", [False, True])
def test_a_group_left_without_a_path_gets_its_removed_edges_back(restore) -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    # One edge, region 0 -> 1: the block needs 4 moves, the waypoint budget is 3, so the
    # first try fails and removing the edge leaves no path to the goal region.
    graph = CodeGraph.from_transitions(torch.tensor([[0]]), torch.tensor([[1]]), oracle.code_sizes)
    policy = make_policy(env, graph, waypoint_budget=3, max_misses=None, restore_when_stuck=restore)
    tasks = one_object_tasks([(0, 0)], [(0, 5)])
    result = evaluate_policy(env, policy, tasks, max_steps=30, tasks_per_rollout=1, seed=0)
    (record,) = result["records"]
    if restore:  # the edge comes back and the second try gets there
        assert record["outcome"] == "solved" and record["edge_removals"] == 1
        assert record["waypoints"] == 1 and record["steps"] >= 5
    else:
        assert record["outcome"] == "no_path" and record["group"] == 0
        assert record["edge_removals"] == 1 and record["waypoint_steps"] == 3


def test_records_count_removals_and_steps_per_phase_of_a_solved_task() -> None:
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=0)
    policy = make_policy(env)
    tasks = make_task_set(env, 2, seed=3)
    result = evaluate_policy(env, policy, tasks, tasks_per_rollout=2, seed=0)
    records = result["records"]
    assert [r["outcome"] == "solved" for r in records] == result["success"]
    assert any(result["success"])
    for record, steps in zip(records, result["steps"], strict=True):
        phases = record["waypoint_steps"] + record["goal_steps"]
        if record["outcome"] in ("solved", "step_limit"):
            # Each step was planned in one phase, up to the step the task ended on.
            assert phases == steps
        else:  # given up on the way: no planning from then on
            assert record["phase"] == "failed" and phases < steps
        assert record["waypoints"] <= record["plans"]


def test_worker_processes_give_the_records_of_one_process() -> None:
    make_env = functools.partial(ObjectRearrangementEnv, num_objects=1, batch_size=(2,), seed=0)
    tasks = make_task_set(make_env(), 4, seed=0)
    graph = CodeGraph.from_play_data(
        collect_play_data(make_env(), 3000, seed=0), OracleCodeEncoder(make_env())
    )
    factory = functools.partial(make_policy, graph=graph)
    one = evaluate_parallel(make_env, factory, tasks, seed=0, max_steps=6, tasks_per_rollout=2)
    two = evaluate_parallel(
        make_env, factory, tasks, seed=0, max_steps=6, tasks_per_rollout=2, workers=2
    )
    assert two["workers"] == 2
    assert two["records"] == one["records"]
    assert [r["task"] for r in two["records"]] == [0, 1, 2, 3]


def test_pooled_rows_keep_each_seeds_records_and_tasks_csv_has_a_line_per_task(tmp_path) -> None:
    def row(seed, outcomes):
        records = [
            {"task": i, "outcome": o, "steps": 5 if o == "solved" else 9, "edge_removals": i}
            for i, o in enumerate(outcomes)
        ]
        success = [o == "solved" for o in outcomes]
        return dict(setting="1obj", method="dorp", low_level="gt", tasks=2, seed=seed,
                    seconds_per_task=1.0, per_task=dict(success=success, steps=[5, 9],
                    lower_bound=[3, 4], records=records))  # fmt: skip

    rows = [row(0, ["solved", "no_path"]), row(1, ["solved", "step_limit"])]
    (pooled,) = pool_seeds(rows)
    records = pooled["per_task"]["records"]
    assert [(r["seed"], r["task"], r["outcome"]) for r in records] == [
        (0, 0, "solved"), (0, 1, "no_path"), (1, 0, "solved"), (1, 1, "step_limit")
    ]  # fmt: skip
    path = write_task_records(rows, tmp_path / "tasks.csv")
    with path.open() as f:
        lines = list(csv.DictReader(f))
    assert [(x["seed"], x["task"], x["outcome"], x["lower_bound"]) for x in lines] == [
        ("0", "0", "solved", "3"), ("0", "1", "no_path", "4"),
        ("1", "0", "solved", "3"), ("1", "1", "step_limit", "4"),
    ]  # fmt: skip
    assert [x["edge_removals"] for x in lines] == ["0", "1", "0", "1"]
    assert {x["low_level"] for x in lines} == {"gt"}


def test_tasks_csv_and_failure_section_tell_apart_one_method_through_two_low_levels(
    tmp_path,
) -> None:
    def row(low_level, outcome):
        records = [{"task": 0, "outcome": outcome, "steps": 7}]
        return dict(setting="5obj", method="dorp", low_level=low_level, tasks=1,
                    per_task=dict(success=[outcome == "solved"], steps=[7],
                    lower_bound=[5], records=records))  # fmt: skip

    rows = [row("gt", "step_limit"), row("checkpoint", "solved")]
    with write_task_records(rows, tmp_path / "tasks.csv").open() as f:
        lines = list(csv.DictReader(f))
    assert [(x["low_level"], x["outcome"]) for x in lines] == [
        ("gt", "step_limit"),
        ("checkpoint", "solved"),
    ]
    section = failure_section(rows)
    assert "5obj dorp (gt): 0 of 1 solved" in section
    assert "5obj dorp (checkpoint): 1 of 1 solved" in section


def test_summaries_refuse_what_is_not_a_record() -> None:
    with pytest.raises(ValueError, match="record 1 must be a dict with an 'outcome'"):
        summarize_failures([{"task": 0, "outcome": "solved"}, {"task": 1}])
