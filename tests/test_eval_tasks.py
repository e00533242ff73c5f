"""Task sets and the evaluation harness."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictBase

from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.eval import evaluate_policy, make_task_set


def greedy_one_object(td: TensorDictBase) -> TensorDictBase:
    """Moves the single block one cell toward its goal: rows first, then columns."""
    diff = td["goal_state"][..., 0, :] - td["state"][..., 0, :]
    action = torch.where(
        diff[..., 0] != 0,
        torch.where(diff[..., 0] < 0, 0, 1),
        torch.where(diff[..., 1] < 0, 2, 3),
    )
    td["action"] = action.unsqueeze(-1).to(torch.int64)
    return td


def test_task_sets_are_seeded_and_leave_the_env_generator_alone() -> None:
    env = ObjectRearrangementEnv(num_objects=2, seed=3)
    before = env.rng.get_state()
    a, b = make_task_set(env, 20, seed=0), make_task_set(env, 20, seed=0)
    assert torch.equal(env.rng.get_state(), before)
    assert torch.equal(a["state"], b["state"]) and torch.equal(a["goal_state"], b["goal_state"])
    c = make_task_set(env, 20, seed=1)
    assert not torch.equal(a["state"], c["state"])
    assert bool((a["lower_bound"] > 0).all())
    assert torch.equal(a["lower_bound"], env.lower_bound_steps(a["state"], a["goal_state"]))
    assert not bool(env.invalid_states(a["goal_state"]).any())
    with pytest.raises(ValueError, match="num_tasks"):
        make_task_set(env, 0)


def test_key_room_goals_show_the_key_taken() -> None:
    tasks = make_task_set(KeyWallEnv(), 10, seed=0)
    assert bool((tasks["goal_state"][:, 2] == 1).all()) and bool((tasks["state"][:, 2] == 0).all())


@pytest.mark.parametrize("per_rollout", [1, 4])
def test_an_optimal_policy_succeeds_in_the_lower_bound(per_rollout: int) -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(), batch_locked=False)
    tasks = make_task_set(env, 6, seed=0)
    result = evaluate_policy(env, greedy_one_object, tasks, tasks_per_rollout=per_rollout)
    assert result["success"] == [True] * 6
    assert result["steps"] == tasks["lower_bound"].tolist()
    assert result["success_rate"] == 1.0
    assert result["mean_steps"] == pytest.approx(result["mean_lower_bound"])


def test_too_few_steps_count_as_failure_at_the_limit() -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(), batch_locked=False)
    tasks = make_task_set(env, 30, seed=0)
    tasks = tasks[tasks["lower_bound"] > 3]
    result = evaluate_policy(env, greedy_one_object, tasks, max_steps=3, tasks_per_rollout=5)
    assert result["success_rate"] == 0.0 and set(result["steps"]) == {3}
    assert result["num_tasks"] == tasks.shape[0]


def test_a_batch_locked_env_must_match_tasks_per_rollout() -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,))
    tasks = make_task_set(env, 6, seed=0)
    with pytest.raises(ValueError, match="tasks_per_rollout"):
        evaluate_policy(env, greedy_one_object, tasks, tasks_per_rollout=2)
    result = evaluate_policy(env, greedy_one_object, tasks, tasks_per_rollout=4)  # pads 6 -> 8
    assert result["num_tasks"] == 6 and result["success_rate"] == 1.0
    with pytest.raises(ValueError, match="goal_state"):
        evaluate_policy(env, greedy_one_object, TensorDict(state=tasks["state"], batch_size=[6]))
