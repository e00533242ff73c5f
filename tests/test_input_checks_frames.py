"""Frames entering a planner or a policy: one check, the same through every entry point.

Goal images and current frames given to :class:`RandomShootingPlanner`,
:class:`CategoricalCEMPlanner` (through their cost's goal), :class:`VisualForesightPolicy`
and the DORP policy (:func:`make_dorp_policy`) go through
:func:`dorp_rl.frames.check_task_frames`: frames no state of the planning env draws
(another environment, another number of objects), all-black frames, NaN frames and float
frames in 0..255 are refused with a message naming the key and the cause; uint8 frames
and float frames of any precision in ``[0, 1]`` are planned with, and give the same plan.
"""

from __future__ import annotations

import pytest
import torch

from dorp_rl.data import collect_play_data
from dorp_rl.envs import (
    GroundTruthModelEnv,
    KeyCorridorEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    OracleCodeEncoder,
    VideoModelEnv,
)
from dorp_rl.frames import check_task_frames, frames_to_uint8
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeGraph,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import VisualForesightPolicy, make_dorp_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHAPE = {"planning_horizon": 3, "num_candidates": 64, "seed": 0}


@pytest.fixture(scope="module")
def one_object():
    """A 2-env 1-object rearrangement, its oracle encoder and code graph."""
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    oracle = OracleCodeEncoder(env)
    graph = CodeGraph.from_play_data(collect_play_data(env, 1000, seed=0), oracle)
    return env, oracle, graph


def make_entry(name: str, env, oracle, graph):
    """The entry point ``name`` for the acting ``env`` (planning through its true dynamics)."""
    planning = GroundTruthModelEnv(env)
    if name == "rs":
        return RandomShootingPlanner(planning, PixelDistanceCost(), **SHAPE)
    if name == "cem":
        return CategoricalCEMPlanner(planning, PixelDistanceCost(), optim_steps=2, top_k=8, **SHAPE)
    if name == "vf-rs":
        return VisualForesightPolicy(planning, "rs", **SHAPE)
    if name == "vf-cem":
        return VisualForesightPolicy(planning, "cem", top_k=8, **SHAPE)
    return make_dorp_policy(env, oracle, graph, **SHAPE)


ENTRIES = ["rs", "cem", "vf-rs", "vf-cem", "dorp"]


def bad_frames(kind: str, env) -> torch.Tensor:
    """Frames ``[2, 3, 16, 16]`` that cannot belong to a 1-object rearrangement task."""
    if kind == "key-wall":
        return KeyWallEnv(batch_size=(2,), seed=0).reset()["goal_pixels"]
    if kind == "two-objects":
        return ObjectRearrangementEnv(2, batch_size=(2,), seed=0).reset()["goal_pixels"]
    if kind == "block-cut":  # the env's colour, but a 2 x 3 block where blocks are 2 x 4
        frames = env.reset()["goal_pixels"].clone()
        frames[:, :, :, :] = 0
        frames[:, :, :2, :3] = env.colours[0].view(1, 3, 1, 1)
        return frames
    if kind == "black":
        return torch.zeros(2, 3, 16, 16, dtype=torch.uint8)
    if kind == "nan":
        return torch.full((2, 3, 16, 16), float("nan"))
    assert kind == "float-0-255"
    return env.reset()["goal_pixels"].float()


BAD = {
    "key-wall": r"no valid state of ObjectRearrangementEnv with 1 object\(s\) draws.*"
    r"colours \[\[128, 128, 128\]",
    "two-objects": r"no valid state of ObjectRearrangementEnv with 1 object\(s\).*"
    r"colours \[\[0, 255, 255\]\] are not among",
    "block-cut": r"no valid state of .* draws .*its colours are the env's, but no valid",
    "black": r"all-black frame",
    "nan": r"hold NaN",
    "float-0-255": r"floats with values in \[0, 255\]: float frames must lie in \[0, 1\]",
}


@pytest.mark.parametrize("entry", ENTRIES)
@pytest.mark.parametrize("kind", list(BAD))
@pytest.mark.parametrize("key", ["goal_pixels", "pixels"])
def test_frames_that_cannot_belong_to_the_task_are_refused_everywhere(one_object, entry, kind, key):
    env, oracle, graph = one_object
    policy = make_entry(entry, env, oracle, graph)
    td = env.reset()
    td[key] = bad_frames(kind, env)
    with pytest.raises(ValueError, match=rf"^{key} .*{BAD[kind]}"):
        policy(td)


def test_a_two_object_policy_refuses_a_one_object_goal():
    """Colours of the env, but one block short: no 2-object state draws it."""
    env = ObjectRearrangementEnv(2, batch_size=(2,), seed=0)
    td = env.reset()
    td["goal_pixels"] = ObjectRearrangementEnv(1, batch_size=(2,), seed=0).reset()["goal_pixels"]
    policy = VisualForesightPolicy(GroundTruthModelEnv(env), "rs", **SHAPE)
    with pytest.raises(ValueError, match=r"2 object\(s\) draws .*colours are the env's"):
        policy(td)


@pytest.mark.parametrize(
    ("acting", "other"),
    [(KeyWallEnv, KeyCorridorEnv), (KeyCorridorEnv, KeyWallEnv)],
    ids=["corridor-goal-to-wall", "wall-goal-to-corridor"],
)
def test_a_key_room_goal_of_another_layout_is_refused(acting, other):
    env = acting(batch_size=(2,), seed=0)
    td = env.reset()
    td["goal_pixels"] = other(batch_size=(2,), seed=0).reset()["goal_pixels"]
    policy = RandomShootingPlanner(GroundTruthModelEnv(env), PixelDistanceCost(), **SHAPE)
    with pytest.raises(ValueError, match=rf"no valid state of {acting.__name__} draws"):
        policy(td)


def test_a_world_model_planner_refuses_colours_outside_its_palette():
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
    policy = VisualForesightPolicy(VideoModelEnv(model, env.num_actions), "rs", **SHAPE)
    td = env.reset()
    td["goal_pixels"] = KeyWallEnv(batch_size=(2,), seed=0).reset()["goal_pixels"]
    with pytest.raises(ValueError, match=r"goal_pixels .*world model cannot show.*128, 128, 128"):
        policy(td)
    td = env.reset()
    td["pixels"] = td["pixels"].double()  # 0..255 as float64
    with pytest.raises(ValueError, match=r"pixels are floats with values in \[0, 255\]"):
        policy(td)


def one_step_task(env: ObjectRearrangementEnv):
    """The block at (0, 0), its goal one cell down: action 1 solves it in one step."""
    from tensordict import TensorDict

    task = TensorDict(
        state=torch.tensor([[[0, 0]]] * 2), goal_state=torch.tensor([[[1, 0]]] * 2), batch_size=(2,)
    )
    return env.reset(task, set_state=True)


DTYPES = [torch.uint8, torch.float32, torch.float64, torch.float16]


@pytest.mark.parametrize("entry", ENTRIES)
@pytest.mark.parametrize("dtype", DTYPES, ids=str)
def test_uint8_and_unit_float_frames_of_any_precision_give_the_same_real_plan(
    one_object, entry, dtype
):
    env, oracle, graph = one_object
    td = one_step_task(env)
    given = {}
    for key in ("pixels", "goal_pixels"):
        frames = td[key]
        given[key] = frames if dtype == torch.uint8 else (frames.to(dtype) / 255).to(dtype)
        td[key] = given[key]
    out = make_entry(entry, env, oracle, graph)(td)
    assert out["action"].tolist() == [[1], [1]]  # the move that reaches the goal
    stepped = env.step(out.select("state", "goal_state", "step_count", "action"))
    assert stepped["next", "success"].all()
    for key, value in given.items():  # the caller's frames are left as given
        assert out[key] is value or torch.equal(out[key], value)


@pytest.mark.parametrize("dtype", DTYPES[1:], ids=str)
def test_float_frames_are_read_as_the_uint8_frames_they_scale(dtype):
    env = ObjectRearrangementEnv(3, batch_size=(), batch_locked=False, seed=0)
    frames = env.render_state(env.sample_states((32,)))
    assert torch.equal(frames_to_uint8(frames.to(dtype) / 255), frames)
    planning = GroundTruthModelEnv(env)
    assert torch.equal(check_task_frames(frames.to(dtype) / 255, "x", planning), frames)


@pytest.mark.parametrize("horizon", [2, 6])
def test_frames_are_checked_once_per_call_not_per_imagined_step(horizon, monkeypatch):
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    calls = []
    original = env.check_frame
    monkeypatch.setattr(env, "check_frame", lambda f, n: calls.append(n) or original(f, n))
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=horizon, num_candidates=8
    )
    planner(env.reset())
    assert sorted(calls) == ["goal_pixels", "pixels"]


@pytest.mark.parametrize("make", [ObjectRearrangementEnv, KeyWallEnv, KeyCorridorEnv])
def test_every_render_of_a_valid_state_passes_the_frame_check(make):
    env = make(batch_size=(), batch_locked=False, seed=0)
    frames = env.render_state(
        torch.cat([env.sample_states((256,)), env.sample_goal_states((256,))])
    )
    assert not env.invalid_frames(frames).any()
    env.check_frame(frames)


# ---------------------------------------------------------------- models and encoders
@pytest.fixture(scope="module")
def video_model():
    torch.manual_seed(0)
    env = ObjectRearrangementEnv(2, batch_size=(), batch_locked=False, seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small()).eval()
    return env, model


@pytest.mark.parametrize("dtype", DTYPES[1:], ids=str)
def test_the_video_model_takes_float_frames_in_0_1(video_model, dtype):
    """docs/DESIGN.md: models take uint8 frames or floats in [0, 1]."""
    env, model = video_model
    frames = env.render_state(env.sample_states((16,)))
    action = torch.randint(env.num_actions, (16, 1), generator=torch.Generator().manual_seed(0))
    unit = frames.to(dtype) / 255
    assert torch.equal(model.predict(unit, action), model.predict(frames, action))
    assert torch.equal(model.logits(unit, action), model.logits(frames, action))
    actions = action.unsqueeze(1).expand(16, 3, 1)
    assert torch.equal(model.rollout(unit, actions), model.rollout(frames, actions))
    planning = VideoModelEnv(model, env.num_actions)
    assert torch.equal(
        planning.predict_frames(unit, action), planning.predict_frames(frames, action)
    )


def test_the_video_model_refuses_float_frames_in_0_255(video_model):
    env, model = video_model
    frames = env.render_state(env.sample_states((4,)))
    with pytest.raises(ValueError, match=r"pixels are floats with values in \[0, 255\]"):
        model.predict(frames.float(), torch.zeros(4, 1, dtype=torch.int64))


@pytest.mark.parametrize("dtype", DTYPES[1:], ids=str)
@pytest.mark.parametrize("kind", ["learned", "oracle"])
def test_encoders_take_float_frames_of_any_precision(dtype, kind):
    env = ObjectRearrangementEnv(2, batch_size=(), batch_locked=False, seed=0)
    frames = env.render_state(env.sample_states((32,)))
    torch.manual_seed(0)
    if kind == "oracle":
        encoder = OracleCodeEncoder(env)
    else:
        encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8))).eval()
    assert torch.equal(encoder.encode(frames.to(dtype) / 255), encoder.encode(frames))
