"""Input checks at the public boundary: envs, planning, encoders, seeds, batch sizes.

Each wrong input raises ``ValueError`` (or a subclass) naming the argument and what is
allowed, instead of a traceback from deep inside torch or tensordict, or a silently
wrong result. The per-step hot path stays free of these checks: an env's own states
are not re-validated at every step.
"""

from __future__ import annotations

import math

import gymnasium
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import dorp_rl.envs  # noqa: F401  (registers the gymnasium ids)
from dorp_rl.data import UniformRandomPolicy, collect_play_data
from dorp_rl.envs import (
    GroundTruthModelEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    WorldModelEnv,
)
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
from dorp_rl.planners import CodeMatchCost, RandomShootingPlanner
from dorp_rl.planners.costs import PixelDistanceCost
from dorp_rl.policies import VisualForesightPolicy
from dorp_rl.validation import (
    SEED_MAX,
    BatchShapeError,
    MissingKeyError,
    check_batch_size,
    check_float,
    check_int,
    check_seed,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---------------------------------------------------------------- the shared helpers
@pytest.mark.parametrize(
    ("value", "expected"),
    [(3, 3), (3.0, 3), (np.int64(3), 3), (torch.tensor(3), 3)],
)
def test_check_int_takes_integers_of_any_kind(value, expected):
    out = check_int("n", value, low=1)
    assert out == expected and type(out) is int


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (2.5, "n must be an integer >= 1, got 2.5"),
        (True, "n must be an integer >= 1, got True"),
        ("3", "n must be an integer >= 1, got '3'"),
        (math.nan, "n must be an integer >= 1, got nan"),
        (0, "n must be >= 1, got 0"),
    ],
)
def test_check_int_names_the_argument_and_range(value, message):
    with pytest.raises(ValueError, match=message):
        check_int("n", value, low=1)


@pytest.mark.parametrize("value", [math.nan, math.inf, -1.0, 2.0, "0.5", None])
def test_check_float_refuses_out_of_range_and_non_finite(value):
    with pytest.raises(ValueError, match=r"x must be .*in \[0, 1\]"):
        check_float("x", value, low=0.0, high=1.0)


@pytest.mark.parametrize("seed", [-1, 1.5, SEED_MAX + 1, "0", None])
def test_check_seed(seed):
    with pytest.raises(ValueError, match="seed must be"):
        check_seed(seed)
    assert check_seed(None, optional=True) is None and check_seed(SEED_MAX) == SEED_MAX


@pytest.mark.parametrize(
    ("batch_size", "expected"), [(4, (4,)), ((2, 3), (2, 3)), ((), ()), ([5], (5,))]
)
def test_batch_sizes_are_taken_as_shapes(batch_size, expected):
    assert check_batch_size(batch_size) == torch.Size(expected)


@pytest.mark.parametrize("batch_size", [(-1,), (0,), (2.5,), "4", (2, 0)])
def test_bad_batch_sizes_are_refused(batch_size):
    with pytest.raises(ValueError, match="batch_size"):
        check_batch_size(batch_size)


# ---------------------------------------------------------------- env construction
@pytest.mark.parametrize(
    ("make", "name"),
    [
        (lambda: ObjectRearrangementEnv(num_objects=2.7), "num_objects"),
        (lambda: ObjectRearrangementEnv(num_objects="2"), "num_objects"),
        (lambda: ObjectRearrangementEnv(batch_size=(-1,)), "batch_size"),
        (lambda: ObjectRearrangementEnv(batch_size=(0,)), "batch_size"),
        (lambda: KeyWallEnv(batch_size=(2.5,)), "batch_size"),
        (lambda: ObjectRearrangementEnv(seed=-1), "seed"),
        (lambda: KeyWallEnv(seed=1.5), "seed"),
        (lambda: KeyWallEnv(max_steps=2.5), "max_steps"),
        (lambda: ObjectRearrangementEnv(block_shapes=(2.5, 4)), "block_shapes"),
        (lambda: ObjectRearrangementEnv(1, colours=[[0.5, 0.2, 0.1]]), "colours"),
        (lambda: KeyWallEnv(terminate_on_success="no"), "terminate_on_success"),
        (lambda: KeyWallEnv(batch_locked="no"), "batch_locked"),
    ],
)
def test_bad_env_arguments_are_named(make, name):
    with pytest.raises(ValueError, match=name):
        make()


def test_an_int_batch_size_is_a_one_dimensional_batch():
    env = ObjectRearrangementEnv(num_objects=2, batch_size=4, seed=0)
    assert env.batch_size == (4,) and env.rollout(3)["pixels"].shape[:2] == (4, 3)


@pytest.mark.parametrize("seed", [-1, 2.5])
def test_set_seed_and_gymnasium_reset_refuse_bad_seeds(seed):
    with pytest.raises(ValueError, match="seed"):
        KeyWallEnv().set_seed(seed)
    with pytest.raises(ValueError, match="seed"):
        gymnasium.make("dorp_rl/KeyWall-v0").reset(seed=seed)


def test_a_tensordict_of_another_batch_size_names_batch_size():
    env = ObjectRearrangementEnv(2, batch_size=(4,), seed=0)
    td = TensorDict(action=torch.zeros(3, 1, dtype=torch.int64), batch_size=[3])
    with pytest.raises(BatchShapeError, match=r"batch_size \[3\].*batch_size \[4\]") as info:
        env.step(td)
    assert isinstance(info.value, ValueError) and isinstance(info.value, RuntimeError)


# ---------------------------------------------------------------- states written before step
def stepped_with(env, state: torch.Tensor):
    td = env.reset()
    td["state"] = state
    td["action"] = torch.zeros(*env.batch_size, 1, dtype=torch.int64)
    return env.step(td)


@pytest.mark.parametrize(
    ("make", "state", "match"),
    [
        (
            lambda: ObjectRearrangementEnv(2, batch_size=(2,), seed=0),
            [[[0, 0], [0, 0]]] * 2,
            "overlap",
        ),
        (lambda: ObjectRearrangementEnv(1, batch_size=(2,), seed=0), [[[15, 14]]] * 2, "inside"),
        (lambda: KeyWallEnv(batch_size=(2,), seed=0), [[0, 8, 0]] * 2, "wall"),
        (lambda: KeyWallEnv(batch_size=(2,), seed=0), [[3, 3, 2]] * 2, "has-key"),
        (lambda: KeyWallEnv(batch_size=(2,), seed=0), [[3, 12, 0]] * 2, "unlocked room"),
    ],
    ids=["overlap", "off-grid", "wall", "key-flag", "locked-room"],
)
def test_an_invalid_state_written_before_step_is_refused(make, state, match):
    with pytest.raises(ValueError, match=rf"^state holds .*{match}"):
        stepped_with(make(), torch.tensor(state))


@pytest.mark.parametrize(
    ("state", "match"),
    [
        (torch.zeros(2, 3, 2, dtype=torch.int64), r"state must have shape \[\*B, 2, 2\]"),
        (torch.zeros(2, 2, 2), "state must have dtype torch.int64"),
    ],
)
def test_a_state_of_the_wrong_layout_is_refused(state, match):
    env = ObjectRearrangementEnv(2, batch_size=(2,), seed=0)
    state[..., 1, :] = 5  # valid positions, wrong layout
    with pytest.raises(ValueError, match=match):
        stepped_with(env, state)


def test_a_state_changed_in_place_is_checked_too():
    env = ObjectRearrangementEnv(2, batch_size=(2,), seed=0)
    td = env.reset()
    td["state"][0] = torch.tensor([[4, 4], [4, 4]])  # in place: same tensor, new version
    td["action"] = torch.zeros(2, 1, dtype=torch.int64)
    with pytest.raises(ValueError, match="batch index \\[0\\]"):
        env.step(td)


def test_a_valid_state_written_before_step_is_stepped_correctly():
    env = KeyWallEnv(batch_size=(2,), seed=0)
    state = torch.tensor([[3, 3, 0], [7, 9, 1]])
    out = stepped_with(env, state)["next", "state"]
    assert torch.equal(out, env.transition(state, torch.zeros(2, dtype=torch.int64)))


def test_step_without_a_state_names_it():
    env = KeyWallEnv(batch_size=(2,), seed=0)
    with pytest.raises(MissingKeyError, match="'state'"):
        env.step(TensorDict(action=torch.zeros(2, 1, dtype=torch.int64), batch_size=[2]))


@pytest.mark.parametrize("make", [lambda: KeyWallEnv, lambda: ObjectRearrangementEnv])
def test_a_rollout_does_not_recheck_the_envs_own_states(make, monkeypatch):
    """The hot path: states the env produced are trusted, so no step reads them back."""
    env = make()(batch_size=(8,), seed=0, max_steps=1000, terminate_on_success=False)
    calls = []
    original = env.invalid_states
    monkeypatch.setattr(env, "invalid_states", lambda s: calls.append(1) or original(s))
    td = env.rollout(25, break_when_any_done=False)
    assert td.shape == (8, 25) and not calls
    given = env.reset(td[:, -1].select("state", "goal_state"), set_state=True)
    assert len(calls) == 2  # a given start and goal are checked, once each
    env.rollout(5, tensordict=given, auto_reset=False)
    assert len(calls) == 2


# ---------------------------------------------------------------- planning
def rs_policy(planning_env):
    return VisualForesightPolicy(planning_env, "rs", planning_horizon=3, num_candidates=8, seed=0)


@pytest.mark.parametrize(
    ("planning", "expected"),
    [
        (lambda: ObjectRearrangementEnv(2, seed=0), r"\[2, 2\]"),
        (lambda: KeyWallEnv(seed=0), r"\[3\]"),
    ],
    ids=["two-objects", "key-wall"],
)
def test_a_planning_env_of_another_world_is_refused(planning, expected):
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    policy = rs_policy(GroundTruthModelEnv(planning()))
    with pytest.raises(ValueError, match=rf"'state' has shape \[1, 2\] per row.*takes {expected}"):
        env.rollout(2, policy)


def test_a_world_model_env_with_another_action_count_is_refused():
    env = ObjectRearrangementEnv(1, seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours.cpu()])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
    with pytest.raises(ValueError, match="num_actions=2 does not match the model.*4 actions"):
        WorldModelEnv(model, 2)
    assert WorldModelEnv(model, env.num_actions).num_actions == 4


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"max_steps": 0}, "max_steps"), ({"tasks_per_rollout": 0}, "tasks_per_rollout")],
)
def test_evaluate_policy_refuses_bad_limits(kwargs, name):
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    with pytest.raises(ValueError, match=name):
        evaluate_policy(env, rs_policy(GroundTruthModelEnv(env)), make_task_set(env, 1), **kwargs)


def code_rollout(target: list[int], sizes=(8, 8)) -> tuple[CodeMatchCost, TensorDict]:
    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=sizes))
    frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
    rollout = TensorDict(
        {
            "pixels": frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16),
            "subgoal_code": torch.tensor(target).expand(2, 5, 4, len(target)),
            ("next", "pixels"): frames,
        },
        batch_size=(2, 5, 4),
    )
    return CodeMatchCost(encoder), rollout


@pytest.mark.parametrize(
    ("target", "sizes", "message"),
    [
        ([9, 0], (8, 8), "code 9 for one-hot 0, which has 8 codes"),
        ([0, -1], (8, 8), "code -1 for one-hot 1, which has 8 codes"),
        ([0, 2], (16, 2), "code 2 for one-hot 1, which has 2 codes"),
    ],
)
def test_an_out_of_range_code_target_is_refused(target, sizes, message):
    cost, rollout = code_rollout(target, sizes)
    with pytest.raises(ValueError, match=message):
        cost(rollout)


def test_a_target_on_a_one_hot_that_is_not_chosen_is_not_read():
    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
    _, rollout = code_rollout([0, 99])
    cost = CodeMatchCost(encoder, onehots=[0])(rollout)["cost"]
    assert cost.shape == (2, 5, 4) and bool(torch.isfinite(cost).all())


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_candidates": 2.5}, "num_candidates"),
        ({"planning_horizon": 0}, "planning_horizon"),
        ({"seed": -1}, "seed"),
    ],
)
def test_planner_arguments_are_named(kwargs, name):
    env = ObjectRearrangementEnv(1, seed=0)
    options = {"planning_horizon": 3, "num_candidates": 8, "seed": 0} | kwargs
    with pytest.raises(ValueError, match=name):
        RandomShootingPlanner(GroundTruthModelEnv(env), PixelDistanceCost(), **options)


@pytest.mark.parametrize(
    "call",
    [
        lambda: make_task_set(KeyWallEnv(), 2, seed=-1),
        lambda: UniformRandomPolicy(4, seed=-1),
        lambda: collect_play_data(KeyWallEnv(batch_size=(2,)), 10, seed=-1),
    ],
    ids=["tasks", "policy", "play-data"],
)
def test_every_seed_argument_is_checked_the_same_way(call):
    with pytest.raises(ValueError, match=r"seed must be in \[0, 9223372036854775807\]"):
        call()


def test_the_largest_seed_works_where_seeds_are_derived():
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 20, seed=SEED_MAX)
    assert len(buffer) == 20


# ---------------------------------------------------------------- encoders
@pytest.fixture(scope="module")
def frames() -> torch.Tensor:
    env = ObjectRearrangementEnv(2, batch_size=(), batch_locked=False, seed=0)
    return env.render_state(env.sample_states((64,)))


@pytest.fixture(scope="module")
def encoder() -> DiscreteCodeEncoder:
    torch.manual_seed(0)
    return DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(16, 16))).eval()


def test_float_frames_in_0_255_are_refused(encoder, frames):
    with pytest.raises(ValueError, match=r"values in \[0, 255\].*must lie in \[0, 1\]"):
        encoder(frames.float())
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        encoder.encode(frames.float())


@pytest.mark.parametrize("bad", [math.nan, -0.1, math.inf])
def test_float_frames_outside_0_1_are_refused(encoder, frames, bad):
    pixels = frames.float() / 255
    pixels[0, 0, 0, 0] = bad
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        encoder(pixels)


def test_float_frames_in_0_1_give_the_uint8_codes(encoder, frames):
    assert torch.equal(encoder.encode(frames.float() / 255), encoder.encode(frames))


def test_numpy_frames_are_taken(encoder, frames):
    assert torch.equal(encoder.encode(frames.numpy()), encoder.encode(frames))
    assert torch.equal(encoder(frames.numpy())[0], encoder(frames)[0])
    palette = torch.tensor([[0, 0, 0], [255, 255, 0], [0, 255, 255]], dtype=torch.uint8)
    model = VideoPredictionModel(8, palette, VideoModelConfig.small())
    action = torch.zeros(64, 1, dtype=torch.int64)
    assert torch.equal(model.predict(frames.numpy(), action), model.predict(frames, action))


@pytest.mark.parametrize(
    ("pixels", "message"),
    [
        (lambda f: f.to(torch.int32), "uint8"),
        (lambda f: f.movedim(-3, -1), r"\[\*B, 3, 16, 16\]"),
        (lambda f: f.tolist(), "torch.Tensor or a numpy array"),
    ],
    ids=["int32", "channel-last", "list"],
)
def test_other_frames_are_refused_by_name(encoder, frames, pixels, message):
    with pytest.raises(ValueError, match=message):
        encoder(pixels(frames))
