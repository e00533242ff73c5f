"""Tests of the native gymnasium versions of the pixel environments."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import dorp_rl.envs  # noqa: F401  (registers the ids)
from dorp_rl.envs import GymnasiumGridEnv

IDS = ["dorp_rl/ObjectRearrangement-v0", "dorp_rl/KeyWall-v0", "dorp_rl/KeyCorridor-v0"]
CASES = [
    ("dorp_rl/ObjectRearrangement-v0", {}),
    ("dorp_rl/ObjectRearrangement-v0", {"num_objects": 3}),
    ("dorp_rl/KeyWall-v0", {}),
    ("dorp_rl/KeyCorridor-v0", {}),
]
CASE_IDS = ["rearrangement-1", "rearrangement-3", "key-wall", "key-corridor"]
# (start, goal, winning action, losing action) one move from the goal.
ONE_MOVE_AWAY = {
    "rearrangement-1": ([[5, 5]], [[5, 6]], 3, 0),
    "rearrangement-3": ([[0, 0], [4, 4], [8, 8]], [[0, 0], [3, 4], [8, 8]], 4, 5),
    "key-wall": ([0, 1, 0], [0, 0, 1], 2, 1),
    "key-corridor": ([0, 9, 1], [0, 10, 1], 3, 2),
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def key_wall():
    """One shared key-wall env for tests that only need some env (each reset starts afresh)."""
    return gymnasium.make("dorp_rl/KeyWall-v0")


def test_import_registers_the_ids():
    for env_id in IDS:
        assert env_id in gymnasium.registry
    env = gymnasium.make("dorp_rl/ObjectRearrangement-v0", num_objects=4)
    assert env.action_space == gymnasium.spaces.Discrete(16)
    assert env.unwrapped.env.num_objects == 4
    assert gymnasium.make("dorp_rl/KeyWall-v0").action_space == gymnasium.spaces.Discrete(4)


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=CASE_IDS)
def test_gymnasium_check_env(env_id, kwargs):
    env = gymnasium.make(env_id, **kwargs)
    check_env(env.unwrapped, skip_render_check=False)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for key in ("pixels", "goal_pixels"):
        assert obs[key].shape == (16, 16, 3) and obs[key].dtype == np.uint8
    assert info["state"].dtype == np.int64
    assert isinstance(info["lower_bound_steps"], int)
    # The bound of a task one move away is 1, of a task already solved 0.
    case = CASE_IDS[CASES.index((env_id, kwargs))]
    start, goal, _, _ = ONE_MOVE_AWAY[case]
    _, info = env.reset(seed=0, options={"state": start, "goal_state": goal})
    assert info["lower_bound_steps"] == 1
    _, info = env.reset(seed=0, options={"state": goal, "goal_state": goal})
    assert info["lower_bound_steps"] == 0


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=CASE_IDS)
def test_same_seed_same_observations(env_id, kwargs):
    def episode(seed):
        env = gymnasium.make(env_id, **kwargs)
        obs, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        frames, states = [obs["pixels"]], [info["state"]]
        for _ in range(10):
            obs, _, _, _, info = env.step(env.action_space.sample())
            frames.append(obs["pixels"])
            states.append(info["state"])
        return env, (np.stack(frames), np.stack(states), obs["goal_pixels"])

    env, a = episode(3)
    _, b = episode(3)
    _, c = episode(4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[1], c[1])
    # Reseeding an existing env restarts its sequence.
    first = env.reset(seed=11)[1]["state"]
    env.reset()
    np.testing.assert_array_equal(env.reset(seed=11)[1]["state"], first)


@pytest.mark.parametrize("case", list(ONE_MOVE_AWAY))
def test_reset_options_and_reaching_the_goal(case):
    env_id, kwargs = CASES[CASE_IDS.index(case)]
    start, goal, win, lose = ONE_MOVE_AWAY[case]
    env = gymnasium.make(env_id, **kwargs)
    torch_env = env.unwrapped.env
    obs, info = env.reset(seed=0, options={"state": start, "goal_state": np.array(goal)})
    np.testing.assert_array_equal(info["state"], start)
    np.testing.assert_array_equal(info["goal_state"], goal)
    want = torch_env.render_state(torch.tensor(start)).permute(1, 2, 0).numpy()
    np.testing.assert_array_equal(obs["pixels"], want)
    want_goal = torch_env.render_state(torch.tensor(goal)).permute(1, 2, 0).numpy()
    np.testing.assert_array_equal(obs["goal_pixels"], want_goal)
    assert info["success"] is False
    assert info["lower_bound_steps"] == 1

    obs, reward, terminated, truncated, info = env.step(lose)
    assert (reward, terminated, truncated, info["success"]) == (0.0, False, False, False)
    env.reset(options={"state": start, "goal_state": goal})
    obs, reward, terminated, truncated, info = env.step(np.int64(win))
    assert (reward, terminated, truncated, info["success"]) == (1.0, True, False, True)
    assert isinstance(reward, float)
    np.testing.assert_array_equal(info["state"], goal)
    np.testing.assert_array_equal(obs["pixels"], obs["goal_pixels"])


def test_reset_options_only_goal_and_bad_options(key_wall):
    env = key_wall
    _, info = env.reset(seed=0, options={"goal_state": [3, 12, 1]})
    np.testing.assert_array_equal(info["goal_state"], [3, 12, 1])
    assert info["state"][2] == 0
    with pytest.raises(ValueError, match="state.*batch index"):
        env.reset(options={"state": [0, 8, 0]})  # in the wall
    with pytest.raises(ValueError, match=r"state must have shape \[\*B, 3\]"):
        env.reset(options={"state": [1, 2]})
    with pytest.raises(ValueError, match="unknown reset options.*'state', 'goal_state'"):
        env.reset(options={"start": [1, 2, 0]})


# BUG (envs/gymnasium_envs.py, GymnasiumGridEnv.reset): options["state"] / ["goal_state"]
# go through torch.as_tensor(..., dtype=torch.int64), which silently truncates floats
# (5.7 -> 5) and bools, so the dtype check of the torch env never sees them.
def test_reset_options_with_non_integer_state_raise():
    env = gymnasium.make("dorp_rl/ObjectRearrangement-v0")
    with pytest.raises(ValueError, match="state"):
        env.reset(options={"state": [[5.7, 5.2]]})


@pytest.mark.parametrize(("env_id", "kwargs"), CASES, ids=CASE_IDS)
def test_rgb_array_render(env_id, kwargs):
    env = gymnasium.make(env_id, render_mode="rgb_array", **kwargs)
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (128, 128, 3) and frame.dtype == np.uint8
    # Each grid cell becomes an 8x8 square of its colour.
    np.testing.assert_array_equal(frame[::8, ::8], obs["pixels"])
    np.testing.assert_array_equal(frame, obs["pixels"].repeat(8, axis=0).repeat(8, axis=1))
    obs, *_ = env.step(0)
    np.testing.assert_array_equal(env.render()[7::8, 7::8], obs["pixels"])
    assert gymnasium.make(env_id, **kwargs).unwrapped.render() is None


def test_render_scale_and_bad_render_mode():
    env = GymnasiumGridEnv("ObjectRearrangement", render_mode="rgb_array", render_scale=3)
    env.reset(seed=0)
    assert env.render().shape == (48, 48, 3)
    with pytest.raises(ValueError, match="render_mode"):
        GymnasiumGridEnv("KeyWall", render_mode="human")
    with pytest.raises(ValueError, match="env_name"):
        GymnasiumGridEnv("Nope")


@pytest.mark.parametrize("bad", [4, -1, 1.5, np.float32(1.0), "1"])
def test_invalid_action_raises(key_wall, bad):
    env = key_wall
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(bad)


def test_step_before_reset_raises():
    env = GymnasiumGridEnv("KeyWall")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_truncation_comes_from_max_steps():
    env = gymnasium.make("dorp_rl/ObjectRearrangement-v0", num_objects=2, max_steps=3)
    env.reset(seed=0, options={"state": [[0, 0], [8, 8]], "goal_state": [[4, 4], [12, 8]]})
    flags = [env.step(0)[2:4] for _ in range(3)]  # block 0 up: stuck at the top edge
    assert flags == [(False, False), (False, False), (False, True)]


def test_sync_vector_env():
    envs = gymnasium.vector.SyncVectorEnv(
        [
            lambda: gymnasium.make("dorp_rl/ObjectRearrangement-v0", num_objects=2, max_steps=2)
            for _ in range(2)
        ]
    )
    obs, info = envs.reset(seed=[0, 1])
    assert obs["pixels"].shape == (2, 16, 16, 3) and obs["pixels"].dtype == np.uint8
    assert info["state"].shape == (2, 2, 2)
    assert not np.array_equal(info["state"][0], info["state"][1])
    obs, reward, terminated, truncated, info = envs.step(np.array([0, 5]))
    assert reward.shape == (2,) and terminated.shape == (2,)
    assert not truncated.any()
    obs, reward, terminated, truncated, info = envs.step(np.array([3, 7]))
    assert (truncated | terminated).all()
    envs.close()
