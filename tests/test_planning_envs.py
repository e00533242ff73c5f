"""Tests of the planning envs: ``GroundTruthModelEnv`` and ``VideoModelEnv``.

The ground-truth model is checked step for step against the acting env it wraps; the
world-model env with fake frame predictors (a per-frame colour shift, and a model that
decodes the block position from the frame and applies the true dynamics).
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.envs.planning import DEFAULT_PREDICT_CHUNK, GroundTruthModelEnv, VideoModelEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class ShiftModel:
    """Adds ``10 * action`` to every byte of the frame (mod 256); records call sizes."""

    def __init__(self) -> None:
        self.calls: list[int] = []

    def predict(self, pixels, action, deterministic=True):
        assert pixels.dim() == 4 and action.shape == (pixels.shape[0], 1)
        self.calls.append(pixels.shape[0])
        shifted = pixels.to(torch.int64) + 10 * action.view(-1, 1, 1, 1)
        return (shifted % 256).to(torch.uint8)


class DecodingModel:
    """A perfect 'video model' of 1-object rearrangement: reads the block, moves it, redraws."""

    def __init__(self, env: ObjectRearrangementEnv) -> None:
        self.env = env

    def predict(self, pixels, action, deterministic=True):
        occupied = pixels.amax(1) > 0  # [N, 16, 16]
        rows = occupied.any(-1).to(torch.int64).argmax(-1)
        cols = occupied.any(-2).to(torch.int64).argmax(-1)
        state = torch.stack([rows, cols], -1).unsqueeze(-2)  # [N, 1, 2]
        return self.env.render_state(self.env.transition(state, action.squeeze(-1)))


def test_specs_and_flags():
    env = ObjectRearrangementEnv(num_objects=2, seed=0)
    for model_env in (GroundTruthModelEnv(env), VideoModelEnv(ShiftModel(), num_actions=8)):
        assert not model_env.batch_locked and model_env.batch_size == torch.Size([])
        check_env_specs(model_env)
        assert model_env.action_spec.n == 8 and model_env.action_spec.dtype == torch.int64
        td = model_env.rollout(3)
        assert not td["next", "done"].any() and not td["next", "terminated"].any()
        assert (td["next", "reward"] == 0).all()


@pytest.mark.parametrize(
    "make_env",
    [
        lambda: ObjectRearrangementEnv(
            num_objects=3, batch_size=(6,), seed=1, terminate_on_success=False
        ),
        lambda: KeyWallEnv(batch_size=(6,), seed=2, terminate_on_success=False),
    ],
    ids=["rearrangement-3", "key-wall"],
)
def test_ground_truth_matches_real_env_step_for_step(make_env):
    env = make_env()
    model = GroundTruthModelEnv(env)
    gen = torch.Generator().manual_seed(0)
    td = env.reset()
    imagined = model.reset(td.select("state", "goal_pixels").clone(), set_state=True)
    assert torch.equal(imagined["pixels"], td["pixels"])
    for _ in range(25):
        action = torch.randint(0, env.num_actions, (6, 1), generator=gen)
        td["action"] = action
        imagined["action"] = action.clone()
        td = env.step(td)
        imagined = model.step(imagined)
        assert torch.equal(imagined["next", "state"], td["next", "state"])
        assert torch.equal(imagined["next", "pixels"], td["next", "pixels"])
        assert torch.equal(imagined["next", "goal_pixels"], td["goal_pixels"])
        td = env.step_mdp(td)
        imagined = model.step_mdp(imagined)


def test_ground_truth_on_two_leading_dims_matches_flat():
    env = ObjectRearrangementEnv(num_objects=2, seed=3)
    model = GroundTruthModelEnv(env)
    state = env.sample_states(torch.Size([3, 5]))
    action = torch.randint(0, 8, (3, 5, 1), generator=torch.Generator().manual_seed(1))
    td = TensorDict(state=state, action=action, batch_size=(3, 5))
    nested = model.step(td)["next"]
    flat = model.step(td.reshape(-1).clone())["next"]
    assert nested.batch_size == torch.Size([3, 5])
    assert torch.equal(nested["state"].reshape(15, 2, 2), flat["state"])
    assert torch.equal(nested["pixels"].reshape(15, 3, 16, 16), flat["pixels"])
    assert torch.equal(nested["pixels"], env.render_state(nested["state"]))


def test_ground_truth_reset_takes_state_and_goal():
    env = ObjectRearrangementEnv(num_objects=1, seed=0)
    model = GroundTruthModelEnv(env)
    state = torch.tensor([[[4, 4]], [[0, 0]]])
    goal = torch.tensor([[[9, 9]], [[1, 1]]])
    out = model.reset(TensorDict(state=state, goal_state=goal, batch_size=(2,)), set_state=True)
    assert torch.equal(out["state"], state)
    assert torch.equal(out["pixels"], env.render_state(state))
    assert torch.equal(out["goal_pixels"], env.render_state(goal))
    with pytest.raises(ValueError, match="state"):
        model.reset(TensorDict(state=torch.tensor([[[15, 15]]]), batch_size=(1,)), set_state=True)


def test_world_model_env_flattens_and_restores_leading_dims():
    model = ShiftModel()
    env = VideoModelEnv(model, num_actions=4)
    gen = torch.Generator().manual_seed(0)
    pixels = torch.randint(0, 256, (2, 3, 4, 3, 16, 16), dtype=torch.uint8, generator=gen)
    action = torch.randint(0, 4, (2, 3, 4, 1), generator=gen)
    goal = torch.randint(0, 256, (2, 3, 4, 3, 16, 16), dtype=torch.uint8, generator=gen)
    td = TensorDict(pixels=pixels, action=action, goal_pixels=goal, batch_size=(2, 3, 4))
    out = env.step(td)["next"]
    assert model.calls == [24]
    assert out["pixels"].shape == (2, 3, 4, 3, 16, 16)
    for index in [(0, 0, 0), (1, 2, 3), (0, 1, 2)]:
        expected = model.predict(pixels[index][None], action[index][None])[0]
        assert torch.equal(out["pixels"][index], expected)
    assert torch.equal(out["goal_pixels"], goal)
    chunked = VideoModelEnv(model, num_actions=4, chunk_size=10)
    model.calls.clear()
    again = chunked.step(td.exclude("next"))["next", "pixels"]
    assert model.calls == [10, 10, 4]
    assert torch.equal(again, out["pixels"])


def test_world_model_env_chunks_large_batches_by_default():
    """A batched evaluation's 10 x 1000 candidates go to the model in calls of at most
    DEFAULT_PREDICT_CHUNK frames (large calls were about 2x slower per frame on a CPU);
    ``chunk_size=None`` makes one call. The frames are the same either way."""
    model = ShiftModel()
    gen = torch.Generator().manual_seed(1)
    n = 2 * DEFAULT_PREDICT_CHUNK + 452
    pixels = torch.randint(0, 256, (n, 3, 16, 16), dtype=torch.uint8, generator=gen)
    action = torch.randint(0, 4, (n, 1), generator=gen)
    chunked = VideoModelEnv(model, num_actions=4).predict_frames(pixels, action)
    assert model.calls == [DEFAULT_PREDICT_CHUNK, DEFAULT_PREDICT_CHUNK, 452]
    model.calls.clear()
    whole = VideoModelEnv(model, num_actions=4, chunk_size=None).predict_frames(pixels, action)
    assert model.calls == [n]
    assert torch.equal(chunked, whole)


def test_video_model_env_is_torchrl_s_model_based_env_around_its_frame_predictor():
    """torchrl's ModelBasedEnvBase steps it: the world model (the predictor as a TensorDict
    module) on a copy of the input; the goal image rides along, the input is untouched."""
    from torchrl.envs.model_based import ModelBasedEnvBase

    from dorp_rl.envs.planning import FramePredictorModel

    env = VideoModelEnv(ShiftModel(), num_actions=4)
    assert isinstance(env, ModelBasedEnvBase) and isinstance(env.world_model, FramePredictorModel)
    gen = torch.Generator().manual_seed(0)
    pixels = torch.randint(0, 256, (2, 5, 3, 16, 16), dtype=torch.uint8, generator=gen)
    td = TensorDict(
        pixels=pixels,
        goal_pixels=pixels.flip(0),
        action=torch.randint(0, 4, (2, 5, 1), generator=gen),
        batch_size=(2, 5),
    )
    out = env.step(td.clone())["next"]
    expected = env.world_model(td.clone())
    assert torch.equal(out["pixels"], expected["pixels"])
    assert torch.equal(out["goal_pixels"], td["goal_pixels"])
    assert not out["done"].any() and not out["reward"].any()
    with pytest.raises(KeyError, match="needs 'pixels'"):
        env.step(td.exclude("pixels"))


def test_world_model_env_with_a_perfect_model_matches_ground_truth():
    env = ObjectRearrangementEnv(num_objects=1, seed=4)
    truth = GroundTruthModelEnv(env)
    learned = VideoModelEnv(DecodingModel(env), num_actions=4)
    state = env.sample_states(torch.Size([8]))
    td_true = TensorDict(state=state, pixels=env.render_state(state), batch_size=(8,))
    td_model = td_true.select("pixels").clone()
    gen = torch.Generator().manual_seed(5)
    for _ in range(10):
        action = torch.randint(0, 4, (8, 1), generator=gen)
        td_true = truth.step_mdp(truth.step(td_true.set("action", action)))
        td_model = learned.step_mdp(learned.step(td_model.set("action", action.clone())))
        assert torch.equal(td_true["pixels"], td_model["pixels"])


def test_world_model_env_reset():
    env = VideoModelEnv(ShiftModel(), num_actions=4)
    assert (env.reset()["pixels"] == 0).all()
    frames = torch.full((2, 3, 16, 16), 7, dtype=torch.uint8)
    out = env.reset(TensorDict(pixels=frames, batch_size=(2,)), set_state=True)
    assert torch.equal(out["pixels"], frames) and out.batch_size == (2,)


@pytest.mark.parametrize(
    "action, message",
    [
        (torch.tensor([[4]]), "action out of range"),
        (torch.tensor([[-1]]), "action out of range"),
        (torch.tensor([[1.0]]), "action must be an integer"),
        (torch.tensor([[True]]), "action must be an integer"),
        (torch.tensor([1]), r"action must have shape \[1, 1\]"),
    ],
)
def test_bad_actions_raise_value_errors(action, message):
    gt = GroundTruthModelEnv(ObjectRearrangementEnv(num_objects=1, seed=0))
    wm = VideoModelEnv(ShiftModel(), num_actions=4)
    state = torch.tensor([[[3, 3]]]).reshape(action.shape[:1] + (1, 2))
    for env, td in (
        (gt, TensorDict(state=state, action=action, batch_size=action.shape[:1])),
        (
            wm,
            TensorDict(
                pixels=torch.zeros(action.shape[:1] + (3, 16, 16), dtype=torch.uint8),
                action=action,
                batch_size=action.shape[:1],
            ),
        ),
    ):
        with pytest.raises(ValueError, match=message):
            env.step(td)


def test_construction_errors():
    with pytest.raises(ValueError, match="GridWorldEnv"):
        GroundTruthModelEnv(VideoModelEnv(ShiftModel(), num_actions=4))
    with pytest.raises(ValueError, match="predict"):
        VideoModelEnv(object(), num_actions=4)
    with pytest.raises(ValueError, match="num_actions"):
        VideoModelEnv(ShiftModel(), num_actions=0)

    class WrongModel:
        def predict(self, pixels, action, deterministic=True):
            return pixels.float()

    env = VideoModelEnv(WrongModel(), num_actions=4)
    td = TensorDict(
        pixels=torch.zeros(2, 3, 16, 16, dtype=torch.uint8),
        action=torch.zeros(2, 1, dtype=torch.int64),
        batch_size=(2,),
    )
    with pytest.raises(ValueError, match="model.predict must return uint8"):
        env.step(td)
    with pytest.raises(KeyError, match="pixels"):
        env.step(td.exclude("pixels"))


def test_world_model_env_predicts_each_distinct_pair_once():
    from dorp_rl.envs import ObjectRearrangementEnv, VideoModelEnv

    class CountingModel:
        """Shifts frames by the action (a deterministic toy) and counts predicted rows."""

        rows = 0

        def predict(self, pixels, action, deterministic=True):
            CountingModel.rows += pixels.shape[0]
            return torch.roll(pixels, shifts=1, dims=-1) + action.view(-1, 1, 1, 1).to(torch.uint8)

    true = ObjectRearrangementEnv(2, batch_size=(), batch_locked=False, seed=0)
    frames = true.render_state(true.sample_states((3,)))
    pixels = frames[torch.tensor([0, 1, 0, 2, 1, 0, 0, 0])]  # 3 distinct frames
    action = torch.tensor([[1], [1], [1], [0], [1], [2], [1], [1]])  # 4 distinct pairs
    td = TensorDict(pixels=pixels, action=action, batch_size=[8])
    plain = VideoModelEnv(CountingModel(), 8, deduplicate=False).step(td.clone())
    assert CountingModel.rows == 8
    CountingModel.rows = 0
    deduped = VideoModelEnv(CountingModel(), 8).step(td.clone())
    assert CountingModel.rows == 4
    assert torch.equal(deduped["next", "pixels"], plain["next", "pixels"])
    with pytest.raises(ValueError, match="deterministic"):
        VideoModelEnv(CountingModel(), 8, deterministic=False, deduplicate=True)
