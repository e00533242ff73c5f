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
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

import dorp_rl.envs  # noqa: F401  (registers the gymnasium ids)
from dorp_rl.data import UniformRandomPolicy, collect_play_data
from dorp_rl.envs import (
    GroundTruthModelEnv,
    KeyCorridorEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    OracleCodeEncoder,
    VideoModelEnv,
    make_env,
)
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeGraph,
    CodeMatchCost,
    NegativeRewardCost,
    RandomShootingPlanner,
    WeightedCostSum,
)
from dorp_rl.planners.costs import PixelDistanceCost
from dorp_rl.policies import AbstractGoalPolicy, VisualForesightPolicy, make_dorp_policy
from dorp_rl.trainers import RepresentationConfig, load_encoder, load_video_model
from dorp_rl.validation import (
    SEED_MAX,
    BatchShapeError,
    MissingKeyError,
    UnknownArgumentError,
    check_batch_size,
    check_device,
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
        VideoModelEnv(model, 2)
    assert VideoModelEnv(model, env.num_actions).num_actions == 4


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


# ---------------------------------------------------------------- weights, budgets, probabilities
@pytest.fixture(scope="module")
def dorp_parts():
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    oracle = OracleCodeEncoder(env)
    graph = CodeGraph.from_play_data(collect_play_data(env, 1000, seed=0), oracle)
    return env, oracle, graph


SMALL = {"planning_horizon": 3, "num_candidates": 16}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"goal_code_weight": math.nan}, r"goal_code_weight must be a finite number >= 0"),
        ({"goal_code_weight": -1.0}, r"goal_code_weight must be >= 0"),
        ({"waypoint_goal_weight": math.nan}, r"waypoint_goal_weight must be a finite number"),
        ({"waypoint_goal_weight": -0.1}, r"waypoint_goal_weight must be >= 0"),
        (
            {"waypoint_step_penalty": math.nan},
            r"^waypoint_step_penalty must be a finite number in \[0, 0.02\)",
        ),
        ({"waypoint_step_penalty": 0.5}, r"^waypoint_step_penalty must be in \[0, 0.02\)"),
        ({"goal_blur_sigmas": (1.0, math.nan)}, r"blur_sigmas\[1\] must be a finite number > 0"),
        ({"waypoint_budget": math.nan}, r"waypoint_budget must be an integer >= 1"),
        ({"waypoint_budget": 0}, r"waypoint_budget must be >= 1"),
        ({"max_removed_edges": -1}, r"max_removed_edges must be >= 0"),
        ({"goal_budget": math.inf}, r"goal_budget must be an integer >= 1 or None"),
        ({"max_misses": 0}, r"max_misses must be >= 1"),
        ({"goal_patience": 2.5}, r"goal_patience must be an integer >= 1 or None"),
        ({"max_reentries": -1}, r"max_reentries must be >= 0"),
        ({"forget_blocked_edges": "no"}, r"forget_blocked_edges must be True or False"),
        (
            {"action_persistence": math.nan},
            r"action_persistence must be a finite number in \[0, 1\)",
        ),
        ({"action_persistence": 1.0}, r"action_persistence must be in \[0, 1\)"),
        ({"num_candidates": math.nan}, r"num_candidates must be an integer >= 1"),
        ({"planning_horizon": 0}, r"planning_horizon must be >= 1"),
        ({"seed": "0"}, r"seed must be"),
        ({"planner": "cem", "top_k": 0}, r"top_k must be in \[1, 16\]"),
        (
            {"planner": "cem", "smoothing": math.nan, "top_k": 4},
            r"smoothing must be a finite number",
        ),
        (
            {"planner": "cem", "warm_start_mix": 1.5, "top_k": 4},
            r"warm_start_mix must be in \[0, 1\]",
        ),
        (
            {"planner": "cem", "min_probability": math.nan, "top_k": 4},
            r"min_probability must be a finite",
        ),
    ],
)
def test_make_dorp_policy_checks_every_weight_budget_and_probability(dorp_parts, kwargs, message):
    env, oracle, graph = dorp_parts
    with pytest.raises(ValueError, match=message):
        make_dorp_policy(env, oracle, graph, **(SMALL | kwargs))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"miss_threshold": math.nan}, r"miss_threshold must be a finite number"),
        ({"goal_code_weight": math.inf}, r"goal_code_weight must be a finite number >= 0"),
        ({"waypoint_budget": -3}, r"waypoint_budget must be >= 1"),
        ({"replan_on_miss": 1}, r"replan_on_miss must be True or False"),
    ],
)
def test_abstract_goal_policy_checks_its_numbers(dorp_parts, kwargs, message):
    env, oracle, graph = dorp_parts
    built = make_dorp_policy(env, oracle, graph, **SMALL)
    options = {"goal_code_weight": 100.0} | kwargs
    with pytest.raises(ValueError, match=message):
        AbstractGoalPolicy(oracle, graph, built.waypoint_planner, built.goal_planner, **options)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (
            lambda p: RandomShootingPlanner(p, PixelDistanceCost(), action_persistence=math.nan),
            "action_persistence",
        ),
        (lambda p: VisualForesightPolicy(p, "rs", action_persistence=-0.5), "action_persistence"),
        (lambda p: VisualForesightPolicy(p, "cem", num_candidates=math.inf), "num_candidates"),
        (lambda p: CategoricalCEMPlanner(p, PixelDistanceCost(), smoothing=math.nan), "smoothing"),
        (lambda p: VisualForesightPolicy(p, "cem", warm_start_mix=math.nan), "warm_start_mix"),
        (lambda p: PixelDistanceCost(blur_sigmas=(math.inf,)), r"blur_sigmas\[0\]"),
        (lambda p: WeightedCostSum({"a": math.nan}), "the weight of 'a'"),
    ],
)
def test_the_planners_check_their_numbers_for_finiteness(make, message):
    planning = GroundTruthModelEnv(ObjectRearrangementEnv(1, seed=0))
    with pytest.raises(ValueError, match=message):
        make(planning)


# ---------------------------------------------------------------- unknown keywords
@pytest.mark.parametrize(
    ("call", "unknown", "listed"),
    [
        (lambda e, o, g: make_dorp_policy(e, o, g, horizon=5, **SMALL), "horizon", "top_k"),
        (
            lambda e, o, g: make_dorp_policy(e, o, g, execution="receding", **SMALL),
            "execution",
            "optim_steps",
        ),
        (
            lambda e, o, g: VisualForesightPolicy(GroundTruthModelEnv(e), "rs", optim_steps=3),
            "optim_steps",
            "action_persistence",
        ),
        (
            lambda e, o, g: VisualForesightPolicy(GroundTruthModelEnv(e), "cem", topk=3),
            "topk",
            "top_k",
        ),
    ],
    ids=["dorp-typo", "dorp-reserved", "vf-rs-cem-only", "vf-cem-typo"],
)
def test_an_unknown_planner_keyword_is_named_with_the_accepted_ones(
    dorp_parts, call, unknown, listed
):
    env, oracle, graph = dorp_parts
    with pytest.raises(UnknownArgumentError, match=rf"\['{unknown}'\].*'{listed}'") as info:
        call(env, oracle, graph)
    assert isinstance(info.value, TypeError) and isinstance(info.value, ValueError)


# ---------------------------------------------------------------- CodeMatchCost one-hots
@pytest.mark.parametrize(
    ("onehots", "message"),
    [
        ((5,), r"onehots must be indices of the encoder's 1 one-hot\(s\) \(0 to 0"),
        ([1], r"onehots must be indices of the encoder's 1 one-hot\(s\)"),
        ((-1,), r"onehots\[0\] must be >= 0"),
        ((0, 0), "each one-hot once"),
        ((0.5,), r"onehots\[0\] must be an integer"),
    ],
)
@pytest.mark.parametrize("kind", ["oracle", "learned"])
def test_code_match_cost_refuses_one_hots_the_encoder_lacks(onehots, message, kind):
    if kind == "oracle":
        encoder = OracleCodeEncoder(ObjectRearrangementEnv(1, seed=0))
    else:
        encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8,)))
    with pytest.raises(ValueError, match=message):
        CodeMatchCost(encoder, onehots=onehots)
    assert CodeMatchCost(encoder, onehots=(0,)).onehots == [0]


# ---------------------------------------------------------------- rewards after done
class EndsEarly(EnvBase):
    """A planning env whose episode ends when action 1 is taken first.

    Step 0: action 0 earns 1 (the episode goes on, earning nothing more), action 1 earns 0
    and ends the episode. Every later step of an ended episode earns 10: a planner that
    counted rewards after ``done`` would end the episode at once.
    """

    def __init__(self) -> None:
        super().__init__(batch_size=())
        self.__dict__["_batch_locked"] = False
        self.observation_spec = Composite(
            t=Unbounded(shape=(1,), dtype=torch.int64),
            over=Categorical(2, shape=(1,), dtype=torch.bool),
        )
        self.action_spec = Categorical(2, shape=(1,), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)

    def _reset(self, td=None, **kwargs):
        shape = td.batch_size if td is not None else torch.Size([])
        zeros = torch.zeros(*shape, 1, dtype=torch.int64)
        return TensorDict(
            t=zeros, over=zeros.bool(), done=zeros.bool(), terminated=zeros.bool(), batch_size=shape
        )

    def _step(self, td):
        t, over, action = td["t"], td["over"], td["action"]
        first = t == 0
        over = torch.where(first, action == 1, over)
        reward = torch.where(first, (action == 0).float(), over.float() * 10)
        return TensorDict(
            t=t + 1,
            over=over,
            reward=reward,
            done=over,
            terminated=over.clone(),
            batch_size=td.batch_size,
        )

    def _set_seed(self, seed):
        pass


def test_negative_reward_cost_ignores_rewards_after_done():
    done = torch.tensor([False, True, False, True]).expand(2, 3, 4).unsqueeze(-1)
    rollout = TensorDict(
        {("next", "reward"): torch.ones(2, 3, 4, 1) * 2, ("next", "done"): done},
        batch_size=(2, 3, 4),
    )
    cost = NegativeRewardCost()(rollout)["cost"]
    assert cost[0, 0].tolist() == [-2.0, -2.0, 0.0, 0.0]  # the done step counts, later ones not
    unmasked = NegativeRewardCost(done_key=None)(rollout)["cost"]
    assert unmasked[0, 0].tolist() == [-2.0] * 4


@pytest.mark.parametrize("planner_cls", [RandomShootingPlanner, CategoricalCEMPlanner])
def test_a_planner_on_rewards_does_not_count_rewards_after_an_early_done(planner_cls):
    env = EndsEarly()
    planner = planner_cls(env, NegativeRewardCost(), planning_horizon=4, num_candidates=32, seed=0)
    out = planner(env.reset(TensorDict(batch_size=(3,))))
    assert out["action"].squeeze(-1).tolist() == [0, 0, 0]  # go on: 1, not end for 0 + 30
    assert out["planner_cost"].squeeze(-1).tolist() == [-1.0, -1.0, -1.0]


# ---------------------------------------------------------------- devices
@pytest.mark.parametrize(
    "make",
    [
        lambda d: ObjectRearrangementEnv(1, device=d),
        lambda d: KeyWallEnv(device=d),
        lambda d: VideoModelEnv(_Still(), 4, device=d),
        lambda d: RepresentationConfig.for_env("rearrangement", 1, device=d),
        lambda d: check_device(d),
        lambda d: UniformRandomPolicy(4, device=d),
        lambda d: load_encoder("no-such-checkpoint.pt", device=d),
        lambda d: load_video_model("no-such-checkpoint.pt", device=d),
    ],
    ids=[
        "rearrangement",
        "key-wall",
        "world-model-env",
        "config",
        "helper",
        "random-policy",
        "load-encoder",
        "load-video-model",
    ],  # fmt: skip
)
def test_a_device_that_does_not_exist_is_refused_by_name(make, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"device must be 'cpu', 'cuda', 'cuda:N' or 'mps'.*'foo'"):
        make("foo")
    with pytest.raises(ValueError, match=r"device='cuda' but CUDA is not available"):
        make("cuda")
    with pytest.raises(ValueError, match=r"device must be .*got 'meta'"):
        make("meta")


def test_a_cuda_index_beyond_the_machine_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"device='cuda:3' but this machine has 1 CUDA device"):
        check_device("cuda:3")
    assert check_device("cuda:0") == torch.device("cuda:0")


def test_dorp_collect_with_a_cuda_device_and_no_cuda_is_a_usage_error(
    tmp_path, monkeypatch, capsys
):
    from dorp_rl.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    argv = ["collect", "--setting", "1obj", "--root", str(tmp_path), "--codes.device", "cuda"]
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert "CUDA is not available" in " ".join(capsys.readouterr().err.split())
    assert not any(tmp_path.iterdir())


class _Still:
    def predict(self, pixels, action, deterministic=True):
        return pixels.clone()


# ---------------------------------------------------------------- rollout lengths, batch sizes
@pytest.mark.parametrize(
    "make",
    [
        lambda: ObjectRearrangementEnv(1, batch_size=(2,), seed=0),
        lambda: KeyWallEnv(seed=0),
        lambda: GroundTruthModelEnv(KeyWallEnv(seed=0)),
        lambda: VideoModelEnv(_Still(), 4),
    ],
    ids=["rearrangement", "key-wall", "ground-truth-model", "world-model"],
)
@pytest.mark.parametrize(
    ("steps", "message"), [(0, "must be >= 1"), (-2, "must be >= 1"), (2.5, "must be an integer")]
)
def test_a_rollout_of_no_steps_names_max_steps(make, steps, message):
    env = make()
    with pytest.raises(ValueError, match=rf"max_steps {message}"):
        env.rollout(steps)
    assert env.rollout(2).shape[-1] == 2


@pytest.mark.parametrize(
    "make",
    [
        lambda b: ObjectRearrangementEnv(1, batch_size=b),
        lambda b: KeyCorridorEnv(batch_size=b),
        lambda b: make_env("key-wall", batch_size=b),
        lambda b: gymnasium.make("dorp_rl/KeyWall-v0", batch_size=b),
    ],
    ids=["rearrangement", "key-corridor", "make_env", "gymnasium"],
)
def test_a_batch_size_given_as_a_string_is_refused_by_name(make):
    with pytest.raises(ValueError, match=r"batch_size.*'8'"):
        make("8")


# ---------------------------------------------------------------- lower bounds
@pytest.mark.parametrize(
    "env", [ObjectRearrangementEnv(2, seed=0), KeyWallEnv(seed=0)], ids=["2obj", "keywall"]
)
def test_lower_bound_steps_refuses_other_shapes_and_states_off_the_grid(env):
    tasks = make_task_set(env, 3, seed=0)
    state, goal = tasks["state"], tasks["goal_state"]
    assert torch.equal(env.lower_bound_steps(state, goal), tasks["lower_bound"])
    with pytest.raises(ValueError, match=r"same shape, got \[1, .*\] and \[3, "):
        env.lower_bound_steps(state[:1], goal)
    off = goal.clone()
    off[0, ..., 0] = 40  # a row below the 16 x 16 grid
    with pytest.raises(ValueError, match="goal_state holds 1 invalid configuration"):
        env.lower_bound_steps(state, off)
    with pytest.raises(ValueError, match="state"):
        env.lower_bound_steps(state.float(), goal)


def test_a_trained_or_loaded_encoder_records_its_environment(tmp_path):
    from dorp_rl.planners import CodeGraph
    from dorp_rl.trainers import RepresentationTrainer

    cfg = RepresentationConfig.for_env("key-wall",
        num_frames=256, num_envs=8, batch_size=16, num_steps=2, log_every=1,
        checkpoint_every=2, diagnostics_every=10**9, progress=False, out_dir=str(tmp_path),
        collapse_check_after=10**9,
    )  # fmt: skip
    trainer = RepresentationTrainer(cfg)
    trainer.train()
    assert trainer.encoder.env_config == KeyWallEnv().config()
    encoder = load_encoder(trainer.checkpoint_path)
    assert encoder.env_config == KeyWallEnv().config()
    corridor = collect_play_data(KeyCorridorEnv(batch_size=(8,)), 128, seed=0)
    with pytest.raises(ValueError, match="the encoder was trained on KeyWallEnv"):
        CodeGraph.from_play_data(corridor, encoder)
