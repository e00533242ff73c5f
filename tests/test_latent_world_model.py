"""The latent world model: frames of any size, torchrl's WorldModel parts and rollouts,
its trainer (checkpoints refused against another env or code sizes, resume), and the
DORP policy and visual foresight planning through it."""

from __future__ import annotations

import csv
import json

import pytest
import torch
from push_blocks import PushBlocksEnv
from tensordict import TensorDict

from dorp_rl.data import EventWindowSampler, collect_play_data, rare_code_changes
from dorp_rl.envs import LatentModelEnv, ObjectRearrangementEnv, planning_dtype
from dorp_rl.integrity import state_digest
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig, LatentModelConfig, LatentWorldModel
from dorp_rl.objectives import LatentWorldModelLoss
from dorp_rl.planners import CodeGraph, LatentGoalCost
from dorp_rl.policies import VisualForesightPolicy, make_dorp_policy, make_planning_env
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    load_encoder,
    load_latent_world_model,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("decoder_kind", ["conv", "mlp"])
@pytest.mark.parametrize("frame_shape", [(3, 24, 32), (1, 8, 8), (3, 10, 13)])
def test_any_frame_size_round_trips_through_latent_code_and_frame(frame_shape, decoder_kind):
    config = LatentModelConfig(
        frame_shape=frame_shape, code_sizes=(6, 2), decoder_kind=decoder_kind
    )
    model = LatentWorldModel(5, config)
    frames = torch.randint(0, 256, (4, *frame_shape), dtype=torch.uint8)
    latent = model.encode(frames)
    assert latent.shape == (4, 128)
    nxt = model.step(latent, torch.tensor([0, 1, 2, 4]))
    assert model.codes(nxt).shape == (4, 2) and model.codes(nxt).dtype == torch.int64
    assert model.decode(nxt).shape == (4, *frame_shape)
    assert model.imagine(latent, torch.zeros(4, 7, dtype=torch.int64)).shape == (4, 7, 128)
    with pytest.raises(ValueError, match="no decoder"):
        LatentWorldModel(5, LatentModelConfig(frame_shape=frame_shape, decoder=False)).decode(
            latent
        )


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("frame_shape", [(3, 10, 13), (1, 16, 16)])
def test_a_convolutional_latent_is_a_map_stepped_alike_everywhere(frame_shape, stride):
    config = LatentModelConfig(
        frame_shape=frame_shape,
        code_sizes=(6, 2),
        dynamics_kind="conv",
        latent_channels=4,
        latent_stride=stride,
        hidden=8,
        decoder_kind="mlp",
    )
    model = LatentWorldModel(5, config)
    c, h, w = frame_shape
    side = lambda n: -(-n // stride)  # noqa: E731 (stride-2 convolutions round up)
    assert model.latent_map == (4, side(h), side(w))
    frames = torch.randint(0, 256, (2, 3, *frame_shape), dtype=torch.uint8)
    latent = model.encode(frames)
    assert latent.shape == (2, 3, 4 * side(h) * side(w)) == (2, 3, model.latent_width)
    actions = torch.tensor([[0, 1, 4], [2, 3, 0]])
    nxt = model.step(latent, actions)
    assert model.codes(nxt).shape == (2, 3, 2) and model.decode(nxt).shape == (2, 3, *frame_shape)
    # Rows are stepped independently: one row alone gives the same next latent.
    torch.testing.assert_close(model.step(latent[1, 2], actions[1, 2]), nxt[1, 2])
    # The same convolution at every cell: with the map's mean held fixed, a map shifted
    # by one cell (away from the borders) steps to the shifted next map.
    grid = torch.zeros(1, 4, 11, 11)
    grid[0, :, 5, 5] = torch.tensor([1.0, -2.0, 0.5, 3.0])
    moved = torch.roll(grid, 1, -1)
    dynamics = model.dynamics
    torch.testing.assert_close(
        torch.roll(dynamics(grid, torch.tensor([2])), 1, -1)[..., 3:-3, 3:-3],
        dynamics(moved, torch.tensor([2]))[..., 3:-3, 3:-3],
    )
    with pytest.raises(ValueError, match="continuous latent map"):
        LatentWorldModel(5, config.replace(slot_dim=8))
    # The convolutions' hidden width is latent_channels unless dynamics_channels says.
    assert model.dynamics.second.in_channels == 4
    wide = LatentWorldModel(5, config.replace(dynamics_channels=7))
    assert wide.dynamics.second.in_channels == 7 and wide.dynamics.out.out_channels == 4
    assert wide.step(latent, actions).shape == latent.shape


@pytest.mark.parametrize("action_planes", [True, False])
def test_map_dynamics_take_the_action_as_planes_or_a_vector_and_any_depth(action_planes):
    # Seeded: with some initialisations every path of a poke through the ReLUs is shut.
    torch.manual_seed(0)
    config = LatentModelConfig(
        frame_shape=(3, 12, 10),
        code_sizes=(5,),
        dynamics_kind="conv",
        latent_channels=3,
        latent_stride=1,
        dynamics_channels=6,
        dynamics_layers=4,
        action_planes=action_planes,
        decoder=False,
    )
    model = LatentWorldModel(7, config)
    first = model.dynamics.first
    # Planes widen the first convolution's input by one channel per action; a vector
    # per action leaves it the map's width.
    assert first.in_channels == 3 + (7 if action_planes else 0)
    assert (model.dynamics.action is None) == action_planes
    # dynamics_layers 3x3 convolutions: each one more cell of sight. A change at one cell
    # reaches the next map only within that many cells of it.
    assert model.dynamics.second is not None and len(model.dynamics.more) == 2
    grid = torch.zeros(2, 3, 12, 10)
    poked = grid.clone()
    poked[:, :, 6, 5] = 1.0
    action = torch.tensor([1, 6])
    with torch.no_grad():
        model.dynamics.mean.weight.zero_()  # only the convolutions carry the poke
        change = (model.dynamics(poked, action) - model.dynamics(grid, action)).abs().sum((0, 1))
    rows, cols = torch.nonzero(change > 0, as_tuple=True)
    assert rows.numel() > 0 and int((rows - 6).abs().max()) == 4 == int((cols - 5).abs().max())
    # Each action steps the latent its own way.
    latent = model.encode(torch.randint(0, 256, (1, 3, 12, 10), dtype=torch.uint8))
    steps = model.step(latent.expand(7, -1), torch.arange(7))
    assert all(not torch.allclose(steps[0], steps[i]) for i in range(1, 7))
    with pytest.raises(ValueError, match="action_planes"):
        LatentModelConfig(action_planes="no")


def test_slots_read_each_one_hots_codes_off_its_own_slot_and_plan():
    config = LatentModelConfig(frame_shape=(3, 10, 13), code_sizes=(4, 6, 5), slot_dim=8, hidden=16)
    model = LatentWorldModel(6, config)
    frames = torch.randint(0, 256, (2, 3, 10, 13), dtype=torch.uint8)
    latent = model.encode(frames)
    assert latent.shape == (2, 24) and model.latent_width == 24
    # Changing slot 1 changes one-hot 1's logits only.
    changed = latent.clone()
    changed[:, 8:16] += 1.0
    before, after = model.code_logits(latent), model.code_logits(changed)
    spans = [(0, 4), (4, 10), (10, 15)]
    for k, (start, end) in enumerate(spans):
        same = torch.equal(before[:, start:end], after[:, start:end])
        assert same is (k != 1), k
    # Each slot is normalised on its own; steps and a torchrl rollout keep the shapes.
    nxt = model.step(latent, torch.tensor([0, 5]))
    slots = nxt.reshape(2, 3, 8)
    torch.testing.assert_close(slots.mean(-1), torch.zeros(2, 3), atol=1e-5, rtol=0)
    env = LatentModelEnv(model, decode=True)
    td = TensorDict(pixels=frames, batch_size=(2,))
    rollout = env.rollout(3, auto_reset=False, tensordict=env.reset(td))
    assert rollout["next", "code"].shape == (2, 3, 3)
    assert rollout["next", "pixels"].shape == (2, 3, 3, 10, 13)
    with pytest.raises(ValueError, match="slot_dim > 0 needs a continuous latent"):
        LatentWorldModel(6, config.replace(latent_groups=4))


def test_soft_targets_score_the_code_head_against_the_encoders_probabilities():
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    window = collect_play_data(env, 80, trajectory_length=10, seed=0)[:80].reshape(8, 10)[:, :3]
    window.set("action", window["action"].reshape(8, 3, 1).long())
    encoder = _encoder()
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    soft = LatentWorldModelLoss(model, encoder, soft_targets=True)
    hard = LatentWorldModelLoss(model, encoder)
    frames = torch.cat([window["pixels"][:, :1], window["next", "pixels"]], 1)
    probs = soft.target_probs(frames)
    assert [p.shape for p in probs] == [(8, 4, 6), (8, 4, 6)]
    # The soft loss is the cross-entropy against those probabilities, which the hard
    # loss (against their argmax) is not, unless the encoder were certain.
    latents = soft.rollout(frames, window["action"][..., 0])
    logits = model.code_logits(latents).split((6, 6), -1)
    expected = sum(
        -(p * part.log_softmax(-1)).sum(-1).mean() for part, p in zip(logits, probs, strict=True)
    )
    torch.testing.assert_close(soft(window)["loss_code"], expected)
    assert not torch.allclose(hard(window)["loss_code"], expected)
    # Probabilities computed beforehand (as the trainer does) give the same loss.
    given = window.clone()
    given.set("code_probs", soft.encode_targets(window["pixels"])[1].reshape(8, 3, 2, 6))
    nxt = soft.encode_targets(window["next", "pixels"])[1].reshape(8, 3, 2, 6)
    given.set(("next", "code_probs"), nxt)
    torch.testing.assert_close(soft(given)["loss_code"], expected)
    # hard_weight adds that weight times the hard loss (the argmax still wins at ties).
    both = LatentWorldModelLoss(model, encoder, soft_targets=True, hard_weight=0.5)
    torch.testing.assert_close(
        both(window)["loss_code"], expected + 0.5 * hard(window)["loss_code"]
    )
    with pytest.raises(ValueError, match="soft_targets"):
        LatentWorldModelLoss(model, encoder, soft_targets="yes")
    with pytest.raises(ValueError, match="hard_weight must be >= 0"):
        LatentWorldModelLoss(model, encoder, soft_targets=True, hard_weight=-1.0)


def test_the_change_term_scores_only_the_values_a_step_changed():
    """``loss_change`` is the decoded frames' squared error at the values that differ from
    the true frame one step before, averaged over those values alone, so a move of a
    few pixels weighs as much as a frame's worth of error."""
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    window = collect_play_data(env, 80, trajectory_length=10, seed=0)[:80].reshape(8, 10)[:, :3]
    window.set("action", window["action"].reshape(8, 3, 1).long())
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    loss = LatentWorldModelLoss(model, _encoder(), change_weight=2.0)
    out = loss(window)
    frames = torch.cat([window["pixels"][:, :1], window["next", "pixels"]], 1).float() / 255
    changed = frames[:, 1:] != frames[:, :-1]
    assert 0 < int(changed.sum()) < 0.1 * changed.numel()  # moves change few values
    decoded = model.decode(loss.rollout(*loss._read(window)))[:, 1:]
    expected = 2.0 * (decoded - frames[:, 1:]).square()[changed].mean()
    torch.testing.assert_close(out["loss_change"], expected)
    # A window where nothing changes has no change term, whatever the decoder draws.
    still = window.clone()
    still.set(("next", "pixels"), window["pixels"][:, :1].expand_as(window["pixels"]).clone())
    still.set("pixels", still["next", "pixels"].clone())
    frozen = loss(still)
    assert float(frozen["loss_change"].detach()) == 0.0
    assert float(frozen["loss_pixels"].detach()) > 0
    out["loss_change"].backward()
    assert model.dynamics[0].weight.grad is not None  # it trains the dynamics too
    assert "loss_change" not in LatentWorldModelLoss(model, _encoder())(window).keys()
    with pytest.raises(ValueError, match="change_weight must be >= 0"):
        LatentWorldModelLoss(model, _encoder(), change_weight=-1.0)


def test_pixel_steps_decode_only_that_many_steps_of_each_window():
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    window = collect_play_data(env, 80, trajectory_length=10, seed=0)[:80].reshape(8, 10)[:, :3]
    window.set("action", window["action"].reshape(8, 3, 1).long())
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    decoded = []  # the hidden layer's inputs: one row per decoded latent
    model.frame_decoder.register_forward_hook(lambda m, i, o: decoded.append(i[0].detach()))
    every = LatentWorldModelLoss(model, _encoder(), change_weight=1.0)(window)
    assert len(decoded[0]) == 8 * 4  # o_t and three imagined steps per window
    # As many steps as the window has (or more) is every step: the same terms.
    whole = LatentWorldModelLoss(model, _encoder(), change_weight=1.0, pixel_steps=4)(window)
    for key in ("loss_pixels", "loss_change"):
        torch.testing.assert_close(whole[key], every[key])
    rows = decoded[0].reshape(8, 4, -1)
    two = LatentWorldModelLoss(model, _encoder(), change_weight=1.0, pixel_steps=2)
    picked = []
    for seed in (0, 1):
        decoded.clear()
        torch.manual_seed(seed)
        out = two(window)
        chosen = decoded[0].reshape(8, 2, 1, -1)
        # two distinct steps of each window's own four
        match = torch.isclose(chosen, rows.unsqueeze(1), atol=1e-5).all(-1)  # [8, 2, 4]
        assert bool((match.sum(-1) == 1).all()) and bool((match.sum(1) <= 1).all())
        picked.append(match.int().argmax(-1))
        # the codes are scored on every step still
        torch.testing.assert_close(out["loss_code"], every["loss_code"])
    assert not torch.equal(picked[0], picked[1])  # other random steps
    with pytest.raises(ValueError, match="pixel_steps must be >= 1"):
        LatentWorldModelLoss(model, _encoder(), pixel_steps=0)


def test_the_mlp_decoder_learns_to_draw_frames():
    """The fast decoder is trained by the loss's pixel term like the convolutional one."""
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    buffer = collect_play_data(env, 200, trajectory_length=10, seed=0)
    config = LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6), decoder_kind="mlp")
    model = LatentWorldModel(8, config)
    loss = LatentWorldModelLoss(model, _encoder())
    window = buffer[:200].reshape(20, 10)[:, :3]
    window.set("action", window["action"].reshape(20, 3, 1).long())
    first = float(loss(window)["loss_pixels"])
    out = _train(loss, window, 40)
    assert float(out["loss_pixels"].detach()) < 0.3 * first
    with pytest.raises(ValueError, match="decoder_kind"):
        LatentModelConfig(decoder_kind="deconv")


def test_a_categorical_latent_stays_one_hot_through_imagination_and_trains():
    config = LatentModelConfig(
        frame_shape=(3, 10, 13), code_sizes=(4,), latent_groups=6, latent_classes=5
    )
    model = LatentWorldModel(3, config)
    frames = torch.randint(0, 256, (2, 3, 10, 13), dtype=torch.uint8)
    latents = model.imagine(model.encode(frames), torch.randint(0, 3, (2, 9)))
    assert latents.shape == (2, 9, 30)
    groups = latents.reshape(2, 9, 6, 5)
    assert bool(((groups == 0) | (groups == 1)).all()) and bool((groups.sum(-1) == 1).all())
    shape = (2, 4, 3, 10, 13)
    window = TensorDict(
        pixels=torch.randint(0, 256, shape, dtype=torch.uint8),
        action=torch.randint(0, 3, (2, 4, 1)),
        next=TensorDict(pixels=torch.randint(0, 256, shape, dtype=torch.uint8), batch_size=[2, 4]),
        batch_size=[2, 4],
    )
    encoder = _encoder(code_sizes=(4,), frame_shape=(3, 10, 13))
    out = LatentWorldModelLoss(model, encoder)(window)
    # The latent term is 0.1 x a cross-entropy over 5 values: near 0.1 x log 5 untrained.
    assert 0.05 < float(out["loss_latent"].detach()) < 0.3
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    assert model.dynamics[0].weight.grad is not None


def test_torchrl_world_model_parts_and_rollout_in_latent_space():
    model = LatentWorldModel(4, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    world = model.as_world_model(decode=True)
    td = TensorDict(pixels=torch.zeros(2, 3, 24, 32, dtype=torch.uint8), batch_size=[2])
    td = world.encode(td)
    td.set("action", torch.tensor([[1], [3]]))
    out = world.step(td)
    assert out["next", "latent"].shape == (2, 128) and out["next", "code"].shape == (2, 2)
    assert out["next", "pixels"].dtype == torch.uint8
    env = LatentModelEnv(model, decode=True, compute_dtype="float32")
    start = env.reset(
        TensorDict(pixels=torch.zeros(3, 3, 24, 32, dtype=torch.uint8), batch_size=[3])
    )
    rollout = env.rollout(5, tensordict=start, auto_reset=False)
    assert rollout.shape == (3, 5) and rollout["next", "pixels"].shape == (3, 5, 3, 24, 32)
    # The latent is stepped, never re-encoded: the same as the model's own imagination.
    actions = rollout["action"][..., 0]
    expected = model.imagine(model.encode(start["pixels"]), actions)
    assert torch.allclose(rollout["next", "latent"], expected, atol=1e-5)
    # Stateless: candidates [b, N] step through the batch_size=() env.
    td = TensorDict(
        pixels=torch.zeros(2, 6, 3, 24, 32, dtype=torch.uint8),
        action=torch.zeros(2, 6, 1, dtype=torch.int64),
        batch_size=[2, 6],
    )
    assert env.step(td)["next", "code"].shape == (2, 6, 2)
    with pytest.raises(ValueError, match=r"\[\*B, 3, 24, 32\]"):
        env.check_frame(torch.zeros(2, 3, 16, 16, dtype=torch.uint8))


def test_the_latent_env_imagines_in_bfloat16_and_writes_float32():
    torch.manual_seed(0)
    model = LatentWorldModel(
        4,
        LatentModelConfig(
            frame_shape=(3, 12, 20), code_sizes=(5, 3), dynamics_kind="conv", latent_stride=2
        ),
    )
    td = TensorDict(pixels=torch.randint(0, 256, (2, 3, 12, 20), dtype=torch.uint8), batch_size=[2])
    actions = torch.randint(0, 4, (2, 7, 5))
    keys = [("next", "latent"), ("next", "code"), ("next", "pixels")]
    exact = LatentModelEnv(model, decode=True, compute_dtype="float32")
    fast = LatentModelEnv(model, decode=True, compute_dtype="bfloat16")
    assert (exact.step_dtype, fast.step_dtype) == (torch.float32, torch.bfloat16)
    want, _ = exact.imagine_candidates(td, actions, keys)
    got, _ = fast.imagine_candidates(td, actions, keys)
    assert got["next", "latent"].dtype == torch.float32
    assert got["next", "pixels"].dtype == torch.uint8
    # bfloat16 keeps 8 bits of mantissa: the same latents to about 1%, not exactly
    error = (got["next", "latent"] - want["next", "latent"]).abs().max()
    assert 0 < error < 0.1 * want["next", "latent"].abs().max()
    frame_error = (got["next", "pixels"].int() - want["next", "pixels"].int()).abs()
    assert frame_error.float().mean() < 2.0
    # the torchrl step path runs in the same dtype and writes float32 latents too
    step = td.clone().set("action", actions[:, 0, :1])
    assert fast.step(step)["next", "latent"].dtype == torch.float32
    assert fast.without_frames().step_dtype == torch.bfloat16
    assert planning_dtype("auto", torch.device("cpu")) in (torch.float32, torch.bfloat16)
    with pytest.raises(ValueError, match="compute_dtype must be one of"):
        LatentModelEnv(model, compute_dtype="float16")


def test_imagined_candidates_equal_stepping_the_latent_env():
    model = LatentWorldModel(4, LatentModelConfig(frame_shape=(3, 10, 13), code_sizes=(5, 3)))
    env = LatentModelEnv(model, decode=True)
    td = TensorDict(pixels=torch.randint(0, 256, (2, 3, 10, 13), dtype=torch.uint8), batch_size=[2])
    actions = torch.randint(0, 4, (2, 5, 4))
    keys = [("next", "code"), ("next", "pixels")]
    rollout, lazy = env.imagine_candidates(td, actions, keys)
    assert lazy == {} and rollout.shape == (2, 5, 4)
    current = td.unsqueeze(1).expand(2, 5).clone()
    codes, frames = [], []
    for t in range(4):
        current.set("action", actions[..., t : t + 1])
        current = env.step(current)
        codes.append(current["next", "code"])
        frames.append(current["next", "pixels"])
        current = env.step_mdp(current)
    assert torch.equal(torch.stack(codes, 2), rollout["next", "code"])
    assert torch.equal(torch.stack(frames, 2), rollout["next", "pixels"])
    # An env that decodes no frames declines a cost that reads them (stepped, then named).
    assert env.without_frames().imagine_candidates(td, actions, keys) is None
    assert env.imagine_candidates(td, actions, [("next", "reward")]) is None


def _train(loss, window, steps):
    """``steps`` Adam steps of ``loss`` on one ``window``; the last step's losses."""
    optimizer = torch.optim.Adam(loss.model.parameters(), lr=3e-3)
    for _ in range(steps):
        out = loss(window)
        optimizer.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optimizer.step()
    return out


def _encoder(code_sizes=(6, 6), frame_shape=(3, 24, 32), seed=0):
    torch.manual_seed(seed)
    config = EncoderConfig.small(code_sizes, frame_shape=frame_shape)
    return DiscreteCodeEncoder(config.replace(channels=8, mlp_sizes=(32,)))


def _config(tmp_path, env="push_blocks:PUSH_BLOCKS", num_objects=None, **overrides):
    values = dict(
        num_frames=480,
        num_envs=4,
        trajectory_length=8,
        horizon=4,
        eval_frames=160,
        eval_sequences=8,
        batch_size=8,
        num_steps=6,
        eval_every=3,
        checkpoint_every=3,
        progress=False,
        out_dir=str(tmp_path / "latent"),
        model={"latent_dim": 16, "channels": 4, "hidden": 16},
    )
    return LatentWorldModelConfig.for_env(env, num_objects, **{**values, **overrides})


def test_the_loss_learns_the_encoders_codes_on_frames_of_another_size():
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    buffer = collect_play_data(env, 400, trajectory_length=10, seed=0)
    encoder = _encoder()
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    loss = LatentWorldModelLoss(model, encoder)
    window = buffer[:400].reshape(40, 10)[:, :5]
    window.set("action", window["action"].reshape(40, 5, 1).long())
    first = loss(window)
    out = _train(loss, window, 30)
    assert float(out["loss_code"].detach()) < 0.5 * float(first["loss_code"].detach())
    # Codes computed beforehand (as the trainer does) give the same loss.
    given = window.clone()
    given.set("code", loss.target_codes(window["pixels"]))
    given.set(("next", "code"), loss.target_codes(window["next", "pixels"]))
    torch.testing.assert_close(loss(given)["loss_code"], loss(window)["loss_code"])
    window.set("action", window["action"] + 8)
    with pytest.raises(ValueError, match=r"actions in \[0, 8\)"):
        loss(window)
    with pytest.raises(ValueError, match="codes of sizes"):
        LatentWorldModelLoss(model, _encoder(code_sizes=(4, 4)))


def test_the_trainer_looks_up_soft_targets_encoded_once(tmp_path):
    encoder = _encoder()
    trainer = LatentWorldModelTrainer(_config(tmp_path, soft_targets=True), encoder=encoder)
    assert set(trainer.target_tables) == {
        "code",
        ("next", "code"),
        "code_probs",
        ("next", "code_probs"),
    }
    batch = trainer.training_batch()
    codes, probs = trainer.loss.encode_targets(batch["next", "pixels"])
    torch.testing.assert_close(batch["next", "code_probs"], probs.reshape(*batch.shape, 2, 6))
    assert torch.equal(batch["next", "code"], codes.reshape(*batch.shape, 2))
    # Hard targets keep only the codes.
    hard = LatentWorldModelTrainer(_config(tmp_path / "hard", soft_targets=False), encoder=encoder)
    assert set(hard.target_tables) == {"code", ("next", "code")}


def test_a_profiles_latent_preset_overrides_its_world_model_windows():
    import dataclasses

    from push_blocks import PUSH_BLOCKS

    profile = dataclasses.replace(
        PUSH_BLOCKS,
        world_model=lambda _: {"horizon": 6, "num_frames": 999, "lr": 0.5},
        latent_model=lambda _: {"num_frames": 1234, "model": {"decoder_kind": "conv"}},
    )
    cfg = LatentWorldModelConfig.for_env(profile)
    # Play windows from the world-model preset (not its other fields), the latent preset
    # over them, the config's defaults for the rest.
    assert (cfg.horizon, cfg.num_frames, cfg.lr) == (6, 1234, 1e-3)
    assert cfg.model.decoder_kind == "conv" and cfg.model.latent_dim == 128
    # The recipe where the profile says nothing: a map stepped by convolutions, an MLP
    # decoder, the encoder's probabilities as targets and a heavier pixel term.
    default = LatentWorldModelConfig.for_env(PUSH_BLOCKS)
    assert (default.model.decoder_kind, default.model.dynamics_kind) == ("mlp", "conv")
    assert (default.pixel_weight, default.soft_targets, default.event_share) == (10.0, True, None)
    # Rearrangement's preset depends on the number of blocks: a finer map when crowded.
    presets = {k: LatentWorldModelConfig.for_env("rearrangement", k) for k in (2, 3, 4, 5)}
    two, three, four, five = (presets[k].model for k in (2, 3, 4, 5))
    assert (two.latent_stride, two.dynamics_channels, two.action_planes) == (4, 64, True)
    assert three == four and presets[3].lr == presets[4].lr == 3e-3
    assert (three.latent_stride, three.latent_channels, three.dynamics_layers) == (2, 16, 3)
    assert not three.action_planes and presets[2].lr == presets[5].lr == 1e-3
    assert (five.latent_stride, five.dynamics_channels, five.action_planes) == (2, 64, True)
    # Crowded blocks: the error where a step changed the frame weighs on its own.
    assert presets[5].change_weight == 10.0 and presets[3].change_weight == 0.0
    # 3-4 blocks train in under 10 minutes: fewer steps, decoding 4 steps of each window.
    assert (presets[3].num_steps, presets[3].pixel_steps) == (5000, 4)
    # 5 blocks and more: twice the steps on twice the play data.
    assert (presets[5].num_steps, presets[5].pixel_steps) == (12_000, 4)
    assert (presets[5].num_frames, presets[3].num_frames) == (400_000, 200_000)


def test_trainer_checkpoints_are_refused_against_another_env_or_code_sizes(tmp_path):
    encoder = _encoder()
    trainer = LatentWorldModelTrainer(_config(tmp_path), encoder=encoder)
    result = trainer.train()
    assert result["step"] == 6 and len(result["evaluation"]["code_accuracy"]) == 4
    assert trainer.model.frame_shape == (3, 24, 32)
    path = tmp_path / "latent" / "checkpoints" / "last.pt"
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    model = load_latent_world_model(path, env, encoder=encoder)
    assert model.code_sizes == (6, 6)
    # The checkpoint knows whose codes it learned: this encoder's, not another's.
    planning = LatentModelEnv(model)
    assert planning.predicts_codes_of(encoder)
    assert not planning.predicts_codes_of(_encoder(seed=1))
    with pytest.raises(ValueError, match="another|environment|env"):
        load_latent_world_model(path, PushBlocksEnv((1, 8, 8), batch_size=(4,), one_hot=True))
    with pytest.raises(ValueError, match="codes of sizes"):
        load_latent_world_model(path, env, encoder=_encoder(code_sizes=(4, 4)))
    # Resume: a longer run goes on from the last checkpoint.
    longer = LatentWorldModelTrainer(_config(tmp_path, num_steps=9), encoder=encoder)
    with pytest.warns(UserWarning, match="num_steps=9"):
        again = longer.train(resume=True)
    assert longer.resumed_from_step == 6 and again["step"] == 9


def test_dorp_and_visual_foresight_plan_through_the_latent_model(tmp_path):
    env = PushBlocksEnv((3, 24, 32), batch_size=(2,))
    encoder = _encoder()
    graph = CodeGraph.from_play_data(
        collect_play_data(env, 400, trajectory_length=10, seed=0), encoder
    )
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    planning = make_planning_env(env, model)
    assert isinstance(planning, LatentModelEnv) and planning.decode
    policy = make_dorp_policy(
        env, encoder, graph, low_level=model, num_candidates=8, planning_horizon=3, seed=0
    )
    # Waypoints are planned on the predicted codes alone: no frame decoded or encoded.
    assert not policy.waypoint_planner.env.decode
    assert ("next", "code") in policy.waypoint_planner.cost.in_keys
    assert ("next", "pixels") not in policy.waypoint_planner.cost.in_keys
    other = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(5, 6)))
    with pytest.raises(ValueError, match="another encoder's codes|this encoder's codes"):
        make_dorp_policy(env, encoder, graph, low_level=other, num_candidates=8)
    rollout = env.rollout(4, policy, break_when_any_done=False)
    assert rollout["action"].shape[:2] == (2, 4)
    vf = VisualForesightPolicy(planning, "rs", num_candidates=8, planning_horizon=3, seed=0)
    assert env.rollout(3, vf, break_when_any_done=False).shape == (2, 3)
    # A planning env given as the low level keeps its compute dtype in every planner.
    exact = LatentModelEnv(model, decode=True, compute_dtype="float32")
    policy = make_dorp_policy(
        env, encoder, graph, low_level=exact, num_candidates=8, planning_horizon=3, seed=0
    )
    for planner in (policy.waypoint_planner, policy.goal_planner):
        assert planner.env.step_dtype == torch.float32
    assert env.rollout(2, policy, break_when_any_done=False).shape == (2, 2)


def test_a_policy_with_another_encoder_plans_through_decoded_frames():
    """A latent model that learned one encoder's codes (an ablation's policy has another
    encoder of the same code sizes): its codes are not read; the frames are encoded."""
    env = PushBlocksEnv((3, 24, 32), batch_size=(2,))
    learned, other = _encoder(), _encoder(seed=1)
    config = LatentModelConfig(
        frame_shape=(3, 24, 32), code_sizes=(6, 6), encoder_digest=state_digest(learned)
    )
    model = LatentWorldModel(8, config)
    for encoder, reads_codes in ((learned, True), (other, False)):
        graph = CodeGraph.from_play_data(
            collect_play_data(env, 200, trajectory_length=10, seed=0), encoder
        )
        policy = make_dorp_policy(
            env, encoder, graph, low_level=model, num_candidates=8, planning_horizon=3, seed=0
        )
        keys = policy.waypoint_planner.cost.in_keys
        assert (("next", "code") in keys) is reads_codes
        assert (("next", "pixels") in keys) is not reads_codes
        assert policy.waypoint_planner.env.decode is not reads_codes
        rollout = env.rollout(3, policy, break_when_any_done=False)
        assert rollout["action"].shape[:2] == (2, 3)


def test_the_goal_phase_through_a_latent_model_is_judged_on_latents_not_frames():
    env = PushBlocksEnv((3, 24, 32), batch_size=(2,))
    encoder = _encoder()
    graph = CodeGraph.from_play_data(
        collect_play_data(env, 200, trajectory_length=10, seed=0), encoder
    )
    model = LatentWorldModel(8, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(6, 6)))
    small = {"num_candidates": 8, "planning_horizon": 3, "seed": 0}
    policy = make_dorp_policy(env, encoder, graph, low_level=model, **small)
    assert policy.config.goal_latent_weight == 1.0
    keys = policy.goal_planner.cost.in_keys
    assert ("next", "latent") in keys and ("next", "pixels") not in keys
    assert any(isinstance(m, LatentGoalCost) for m in policy.goal_planner.cost.modules())
    rollout = env.rollout(3, policy, break_when_any_done=False)
    assert rollout["action"].shape[:2] == (2, 3)
    # 0 keeps the decoded frames' pixel and object-map terms; the true dynamics have no
    # latents, so the term is off there and refused when asked for.
    pixels = make_dorp_policy(env, encoder, graph, low_level=model, goal_latent_weight=0, **small)
    assert ("next", "pixels") in pixels.goal_planner.cost.in_keys
    # A waypoint cost with a goal term judges it on the latents too, whichever way the
    # goal phase judges the goal image: a waypoint call decodes no frame.
    ranked = {"waypoint_goal_weight": 0.01, **small}
    for weight in (None, 0.0):
        latents = make_dorp_policy(
            env, encoder, graph, low_level=model, goal_latent_weight=weight, **ranked
        )
        keys = latents.waypoint_planner.cost.in_keys
        assert ("next", "latent") in keys and ("next", "pixels") not in keys
        assert not latents.waypoint_planner.env.decode
        goal_keys = latents.goal_planner.cost.in_keys
        assert (("next", "pixels") in goal_keys) is (weight == 0.0)
    truth = make_dorp_policy(env, encoder, graph, **small)
    assert truth.config.goal_latent_weight == 0.0
    with pytest.raises(ValueError, match="goal_latent_weight > 0 needs the latent model"):
        make_dorp_policy(env, encoder, graph, goal_latent_weight=1.0, **small)


def test_the_latent_goal_cost_is_lowest_at_the_goal_images_latent():
    model = LatentWorldModel(4, LatentModelConfig(frame_shape=(1, 8, 8), code_sizes=(4,)))
    frames = torch.randint(0, 256, (3, 1, 8, 8), dtype=torch.uint8)
    with torch.no_grad():
        latents = model.encode(frames)  # [3, D]: candidate k ends at frame k's latent
    goal = frames[1].reshape(1, 1, 1, 1, 8, 8).expand(1, 3, 2, 1, 8, 8)
    imagined = torch.stack([latents, latents], 1).unsqueeze(0)  # [1, 3 candidates, 2, D]
    rollout = TensorDict({"goal_pixels": goal, ("next", "latent"): imagined}, batch_size=(1, 3, 2))
    cost = LatentGoalCost(model)(rollout)["cost"][0, :, 0]
    assert float(cost[1]) < 1e-5 and bool((cost[[0, 2]] > 1e-3).all())
    with pytest.raises(ValueError, match=r"must be frames \[1, 8, 8\]"):
        LatentGoalCost(model)(
            TensorDict(
                {"goal_pixels": goal[..., :4], ("next", "latent"): imagined}, batch_size=(1, 3, 2)
            )
        )
    with pytest.raises(ValueError, match="has none"):
        LatentGoalCost(torch.nn.Linear(2, 2))


def test_code_match_cost_reads_predicted_codes_without_frames():
    from dorp_rl.planners import CodeMatchCost

    encoder = _encoder(code_sizes=(6, 6), frame_shape=(3, 24, 32))
    start = torch.randint(0, 256, (1, 3, 24, 32), dtype=torch.uint8)
    start_code = encoder(start)[0][0]
    target = start_code.clone()
    target[0] = (target[0] + 1) % 6  # one-hot 0 must change, one-hot 1 keep its code
    predicted = start_code.expand(1, 2, 3, 2).clone()
    predicted[0, 0, 2, 0] = target[0]  # candidate 0 reaches it at its last step
    predicted[0, 1, 1] = torch.tensor([target[0], (target[1] + 1) % 6])  # 1 moves both
    rollout = TensorDict(
        {
            "pixels": start.reshape(1, 1, 1, 3, 24, 32).expand(1, 2, 3, 3, 24, 32),
            "subgoal_code": target.reshape(1, 1, 1, 2).expand(1, 2, 3, 2),
            ("next", "code"): predicted,
        },
        batch_size=(1, 2, 3),
    )
    cost = CodeMatchCost(encoder, onehots=[0], code_key=("next", "code"))
    assert ("next", "pixels") not in cost.in_keys
    assert cost(rollout)["cost"][0].tolist() == [[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]]


def test_the_command_evaluates_through_a_latent_model_checkpoint(tmp_path, capsys):
    """``dorp evaluate --low-level <latent checkpoint>``: VF plans through the latent
    model of the run's env; a model of another env is a usage error naming it."""
    from dorp_rl.cli import main

    cfg = _config(tmp_path, env="rearrangement", num_objects=1, trajectory_length=16)
    from dorp_rl.envs import OracleCodeEncoder

    env = cfg.make_env(batch_size=(4,))
    LatentWorldModelTrainer(cfg, encoder=OracleCodeEncoder(env, cell_size=4)).train()
    path = str(tmp_path / "latent" / "checkpoints" / "last.pt")
    tiny = ["--root", str(tmp_path / "runs"), "--setting", "1obj", "--tasks", "2",
            "--tasks-per-rollout", "2", "--candidates", "8", "--planning-horizon", "3",
            "--max-steps", "4", "--gifs", "0", "--no-progress"]  # fmt: skip
    main(["evaluate", *tiny, "--methods", "vf-rs", "--low-level", path])
    rows = (tmp_path / "runs" / "demo" / "results.csv").read_text()
    assert "vf-rs" in rows and "checkpoint" in rows
    with pytest.raises(SystemExit) as stop:
        main(["evaluate", *tiny, "--setting", "2obj", "--name", "other", "--low-level", path])
    assert stop.value.code == 2
    assert "was trained on another environment" in capsys.readouterr().err


def test_the_command_trains_a_latent_model_of_the_runs_codes_and_plans_through_it(tmp_path):
    from dorp_rl.cli import main

    root = ["--root", str(tmp_path), "--setting", "1obj", "--no-progress"]
    codes = ["--codes.num-frames", "400", "--codes.num-envs", "8", "--codes.num-steps", "5",
             "--codes.batch-size", "16", "--codes.diagnostics-samples", "64"]  # fmt: skip
    latent = ["--latent-model.num-frames", "320", "--latent-model.num-envs", "4",
              "--latent-model.horizon", "3", "--latent-model.num-steps", "3",
              "--latent-model.eval-frames", "160", "--latent-model.eval-sequences", "4",
              "--latent-model.batch-size", "4"]  # fmt: skip
    tiny = ["--tasks", "2", "--tasks-per-rollout", "2", "--candidates", "8",
            "--planning-horizon", "3", "--max-steps", "4", "--gifs", "0"]  # fmt: skip
    main(
        [
            "evaluate",
            *root,
            *codes,
            *latent,
            *tiny,
            "--methods",
            "dorp",
            "--low-level",
            "latent-model",
        ]
    )
    run = tmp_path / "demo"
    assert (run / "latent_model" / "checkpoints" / "last.pt").is_file()
    rows = (run / "results.csv").read_text()
    assert "latent-model" in rows
    stages = json.loads((run / "stages.json").read_text())
    assert "latent_model" in stages and "evaluate:dorp:latent-model" in stages


def test_the_paper_run_trains_a_latent_model_per_setting_and_seed(tmp_path, dorp):
    """``reproduce --paper --low-level latent-model``: each sub-run trains its own latent
    model of its own codes (seeded like them), and every method, the ablations with
    their other encoders included, plans through it."""
    latent = ("--latent-model.num-frames", "320", "--latent-model.num-envs", "4",
              "--latent-model.horizon", "3", "--latent-model.num-steps", "2",
              "--latent-model.eval-frames", "160", "--latent-model.eval-sequences", "4",
              "--latent-model.batch-size", "4")  # fmt: skip
    dorp(tmp_path, "reproduce", "--paper", "--settings", "1obj", "--seeds", "3",
         "--low-level", "latent-model", *dorp.CODES, *dorp.EVAL, *latent,
         "--gifs", "0")  # fmt: skip
    run = tmp_path / "run"
    with (run / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert {r["low_level"] for r in rows} == {"latent-model"}
    assert {"dorp", "dorp-arbitrary", "vf-rs"} <= {r["method"] for r in rows}
    sub = run / "1obj-seed3"
    stages = json.loads((sub / "stages.json").read_text())
    assert stages["latent_model"]["config"]["latent_model"]["seed"] == 3
    assert stages["latent_model"]["config"]["latent_model"]["num_steps"] == 2
    # The sub-run's model learned the sub-run's codes, and knows it.
    env = ObjectRearrangementEnv(num_objects=1)
    model = load_latent_world_model(sub / "latent_model" / "checkpoints" / "last.pt", env)
    encoder = load_encoder(sub / "codes" / "checkpoints" / "last.pt", env)
    assert model.config.encoder_digest == state_digest(encoder)


class _ShadeCodes(torch.nn.Module):
    """Codes read off PushBlocksEnv frames: one-hot 0 the column of block 0 (mod 8, it
    changes on most of block 0's sideways moves), one-hot 1 whether block 1 is in the
    canvas' lower half (it changes only when block 1 crosses the middle row: rarely)."""

    code_sizes = (8, 2)
    frame_shape = (3, 24, 32)

    def forward(self, frames):
        first = frames[..., 0, :, :]
        column = (first == 250).any(-2).float().argmax(-1) % 8
        lower = ((first == 60).any(-1).float().argmax(-1) >= 12).long()
        codes = torch.stack([column, lower], -1)
        return codes, torch.nn.functional.one_hot(codes, 8).float()


def test_event_windows_of_the_latent_trainer_are_rare_code_changes(tmp_path):
    encoder = _ShadeCodes()
    cfg = _config(tmp_path, num_frames=4000, eval_frames=2000, event_share=0.5, batch_size=64)
    trainer = LatentWorldModelTrainer(cfg, encoder=encoder)
    data = trainer.buffer[: len(trainer.buffer)]
    codes, nxt = encoder(data["pixels"])[0], encoder(data["next", "pixels"])[0]
    events = trainer.transition_events(trainer.buffer.storage)
    # The rare one-hot's changes are the events, the frequent one's are not.
    assert torch.equal(events, codes[:, 1] != nxt[:, 1])
    assert torch.equal(events, rare_code_changes(codes, nxt))
    assert 0 < events.float().mean() < 0.05 < (codes[:, 0] != nxt[:, 0]).float().mean()
    # Counting changed cells finds none of them: every action moves one block one cell.
    assert not EventWindowSampler(4, 0.5).transition_events(trainer.buffer.storage).any()
    batch = trainer.training_batch()
    held = (batch["code"][..., 1] != batch["next", "code"][..., 1]).any(-1)
    assert held.float().mean() >= 0.3  # about 0.5; uniform windows: about 4 x 0.01
    windows = trainer.eval_event_windows
    assert windows is not None and len(windows) > 0
    first, after = encoder(windows["pixels"])[0], encoder(windows["next", "pixels"])[0]
    assert (first[..., 1] != after[..., 1]).any(-1).all()
    assert trainer.evaluate()["event_num_sequences"] == len(windows)


def test_large_frames_are_modelled_at_a_stride_chosen_from_their_size():
    torch.manual_seed(0)
    config = LatentModelConfig.recipe(frame_shape=(3, 64, 70), code_sizes=(4, 4))
    model = LatentWorldModel(5, config)
    # 64 x 70 frames: 4 x 4 blocks, a partial block at the right edge
    assert model.frame_stride == 4 and model.model_frame_shape == (3, 16, 18)
    assert model.config.frame_stride == 4
    frames = torch.randint(0, 256, (2, 3, 64, 70), dtype=torch.uint8)
    decoded = model.decode(model.encode(frames))
    assert decoded.shape == (2, 3, 64, 70)
    # each 4 x 4 block of a decoded frame is one value
    blocks = decoded[..., :64, :68].unflatten(-1, (17, 4)).unflatten(-3, (16, 4))
    assert torch.equal(blocks.amax((-1, -3)), blocks.amin((-1, -3)))
    # a frame upscaled 4-fold reads as the small frame does
    small = torch.randint(0, 256, (2, 3, 16, 16), dtype=torch.uint8)
    big_model = LatentWorldModel(
        5, LatentModelConfig.recipe(frame_shape=(3, 64, 64), code_sizes=(4,))
    )
    small_model = LatentWorldModel(
        5, LatentModelConfig.recipe(frame_shape=(3, 16, 16), code_sizes=(4,), frame_stride=1)
    )
    small_model.load_state_dict(big_model.state_dict())
    big = small.repeat_interleave(4, -2).repeat_interleave(4, -1)
    torch.testing.assert_close(big_model.encode(big), small_model.encode(small))
    # small frames keep every pixel; stored configs without the field read as stride 1
    assert LatentWorldModel(5, LatentModelConfig.recipe(frame_shape=(3, 24, 32))).frame_stride == 1
    stored = LatentWorldModelConfig().to_dict()
    del stored["model"]["frame_stride"]
    assert LatentWorldModelConfig.from_dict(stored).model.frame_stride == 1
