"""Video prediction model, its loss, open-loop metrics and WorldModelTrainer."""

from __future__ import annotations

from unittest import mock

import pytest
import torch
from tensordict import TensorDict

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.data import EventWindowSampler, SequenceSampler, collect_play_data
from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.eval import open_loop_accuracy
from dorp_rl.modules import VideoModelConfig, VideoPredictionModel, palette_from_frames
from dorp_rl.objectives import VideoPredictionLoss
from dorp_rl.objectives.video import gaussian_kl
from dorp_rl.trainers import WorldModelConfig, WorldModelTrainer, load_encoder, load_video_model


@pytest.fixture(scope="module")
def env() -> ObjectRearrangementEnv:
    return ObjectRearrangementEnv(num_objects=2, batch_size=(16,), seed=0)


@pytest.fixture(scope="module")
def windows(env: ObjectRearrangementEnv) -> TensorDict:
    buffer = collect_play_data(env, 512, seed=0, trajectory_length=8, sampler=SequenceSampler(4))
    return buffer.sample(64)


@pytest.fixture(scope="module")
def model(env: ObjectRearrangementEnv, windows: TensorDict) -> VideoPredictionModel:
    torch.manual_seed(0)
    palette = palette_from_frames(windows["pixels"])
    return VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())


def tiny_config(tmp_path, **overrides) -> WorldModelConfig:
    base = WorldModelConfig.for_env(
        "rearrangement",
        1,
        num_steps=6,
        num_frames=512,
        num_envs=16,
        horizon=3,
        trajectory_length=4,
        eval_frames=128,
        eval_sequences=16,
        model=VideoModelConfig.small(),
        batch_size=8,
        log_every=2,
        checkpoint_every=3,
        eval_every=3,
        progress=False,
        out_dir=str(tmp_path / "wm"),
    )
    return base.replace(**overrides)


# ------------------------------------------------------------------ palette and model
def test_palette_is_black_first_and_complete(windows: TensorDict) -> None:
    palette = palette_from_frames(windows["pixels"])
    assert palette.dtype == torch.uint8 and palette.shape == (3, 3)  # black + 2 blocks
    assert palette[0].tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="uint8"):
        palette_from_frames(windows["pixels"].float())
    noise = torch.randint(0, 256, (4, 3, 16, 16), dtype=torch.uint8)
    with pytest.raises(ValueError, match="max_colours"):
        palette_from_frames(noise)


def test_predictions_have_the_right_shapes_and_only_palette_colours(
    model: VideoPredictionModel, windows: TensorDict
) -> None:
    pixels = windows[:, 0]["pixels"]
    action = windows[:, 0]["action"]
    logits = model.logits(pixels, action)
    assert logits.shape == (64, model.num_colours, 16, 16) and logits.dtype == torch.float32
    frame = model.predict(pixels, action)
    assert frame.dtype == torch.uint8 and frame.shape == pixels.shape
    colours = {tuple(c) for c in frame.movedim(1, -1).reshape(-1, 3).tolist()}
    assert colours <= {tuple(c) for c in model.palette.tolist()}
    frames = model.rollout(pixels, windows["action"])
    assert frames.shape == (64, 4, 3, 16, 16)
    # the first rollout step is the one-step prediction
    assert torch.equal(frames[:, 0], frame)


def test_stochastic_mode_uses_the_latent_and_is_seeded(
    env: ObjectRearrangementEnv, windows: TensorDict
) -> None:
    torch.manual_seed(1)
    palette = palette_from_frames(windows["pixels"])
    model = VideoPredictionModel(
        env.num_actions, palette, VideoModelConfig.small(latent_dim=3, prior="learned")
    )
    pixels, action = windows[:, 0]["pixels"], windows[:, 0]["action"]
    z = torch.randn(64, 3) * 5
    # the latent reaches the prediction (FiLM and input channels)
    assert not torch.allclose(model.logits(pixels, action, z), model.logits(pixels, action))
    with torch.no_grad():  # a prior std of about 20, so that draws change the frames
        model.prior_net.head.bias[3:] = 20.0

    def draw(seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        return model.predict(pixels, action, deterministic=False, generator=generator)

    a, b, other = draw(3), draw(3), draw(4)
    assert torch.equal(a, b) and not torch.equal(a, other)
    # A draw is the prior mean plus std times the generator's normal noise; the
    # deterministic mode decodes the mean itself.
    mean, std = model.prior(model.frame_probs(pixels), action)
    assert std.min() > 19.0
    noise = torch.randn(mean.shape, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        drawn = model.frames_from_logits(model.logits(pixels, action, mean + std * noise))
        at_mean = model.frames_from_logits(model.logits(pixels, action, mean))
    assert torch.equal(a, drawn)
    deterministic = model.predict(pixels, action)
    assert torch.equal(deterministic, at_mean) and not torch.equal(deterministic, a)


def test_advection_moves_each_colour_by_its_own_kernel(
    env: ObjectRearrangementEnv, windows: TensorDict
) -> None:
    """An untrained model copies the frame; a kernel head set to "first colour down,
    second colour right" moves exactly those blocks and fills the background in."""
    torch.manual_seed(0)
    palette = palette_from_frames(windows["pixels"])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
    state = torch.tensor([[[4, 4], [10, 8]]])
    pixels = env.render_state(state)
    action = torch.zeros(1, 1, dtype=torch.int64)
    assert torch.equal(model.predict(pixels, action), pixels)
    colour = [model.palette_index(env.render_state(state))[0, r, c] for r, c in state[0].tolist()]
    bias = torch.full((model.num_colours, 9), -30.0)
    bias[:, 4] = 30.0  # identity for every colour ...
    bias[colour[0]] = torch.tensor([-30.0] * 7 + [30.0, -30.0])  # ... tap (2, 1): down
    bias[colour[1]] = torch.tensor([-30.0] * 5 + [30.0] + [-30.0] * 3)  # tap (1, 2): right
    with torch.no_grad():
        model.kernel_head.bias.copy_(bias.flatten())
        model.head.weight.zero_()
        model.head.bias.zero_()
    expected = env.render_state(torch.tensor([[[5, 4], [10, 9]]]))
    assert torch.equal(model.predict(pixels, action), expected)


def test_collision_features_see_blocked_moves(env: ObjectRearrangementEnv) -> None:
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
    # block 0 in the top-left corner, block 1 right below it
    pixels = env.render_state(torch.tensor([[[0, 0], [2, 0]]]))
    features = model._collisions(model.frame_probs(pixels)).view(3, 2, 9)  # colour, kind, tap
    up, down, left, right, stay = 1, 7, 3, 5, 4
    overlap, lost = features[1, 0], features[1, 1]
    assert overlap[down] == 0.5 and overlap[[up, left, right, stay]].eq(0).all()
    assert lost[up] == 0.5 and lost[left] == 0.25 and lost[[down, right, stay]].eq(0).all()
    assert features[2, 0, up] == 0.5 and features[2, 1].sum() == features[2, 1, [3, 6, 0]].sum()


def test_bad_inputs_name_what_was_expected(
    model: VideoPredictionModel, windows: TensorDict
) -> None:
    pixels, action = windows[:, 0]["pixels"], windows[:, 0]["action"]
    with pytest.raises(ValueError, match="uint8"):
        model.predict(pixels.float(), action)
    with pytest.raises(ValueError, match=r"\[N, 3, 16, 16\]"):
        model.predict(pixels[:, :, :8], action)
    with pytest.raises(ValueError, match=r"in \[0, 7\] \(num_actions = 8\)"):
        model.predict(pixels, action + 8)
    with pytest.raises(ValueError, match="integer"):
        model.predict(pixels, action.float())
    with pytest.raises(ValueError, match=r"\[64, 1\]"):
        model.predict(pixels, action[:10])
    with pytest.raises(ValueError, match=r"\[N, H, 1\]"):
        model.rollout(pixels, action)
    with pytest.raises(ValueError, match="distinct"):
        VideoPredictionModel(8, torch.zeros(2, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="preset"):
        VideoModelConfig.preset("huge")


def test_as_tensordict_module_handles_any_leading_shape(
    model: VideoPredictionModel, windows: TensorDict
) -> None:
    module = model.as_tensordict_module()
    td = TensorDict(pixels=windows["pixels"], action=windows["action"], batch_size=[64, 4])
    out = module(td)
    assert out["next", "pixels"].shape == (64, 4, 3, 16, 16)
    assert torch.equal(
        out["next", "pixels"][:, 1], model.predict(td[:, 1]["pixels"], td[:, 1]["action"])
    )


# ------------------------------------------------------------------ loss
def test_gaussian_kl_is_zero_only_for_equal_distributions() -> None:
    mean, std = torch.randn(5, 3), torch.rand(5, 3) + 0.1
    assert torch.allclose(gaussian_kl(mean, std, mean, std), torch.zeros(5, 3), atol=1e-6)
    assert bool((gaussian_kl(mean + 1.0, std, mean, std) > 0).all())
    assert bool((gaussian_kl(mean, std * 2, mean, std) > 0).all())


def test_loss_outputs_and_missing_key(model: VideoPredictionModel, windows: TensorDict) -> None:
    loss = VideoPredictionLoss(model, open_loop_length=2)
    out = loss(windows)
    assert {"loss_reconstruction", "loss_kl", "frame_accuracy", "pixel_accuracy"} <= set(out.keys())
    assert out["loss_reconstruction"].requires_grad
    assert not out["frame_accuracy"].requires_grad
    with pytest.raises(KeyError, match="action"):
        loss(windows.exclude("action"))
    with pytest.raises(ValueError, match="open_loop_length"):
        VideoPredictionLoss(model, open_loop_length=0)


def test_loss_falls_on_a_tiny_dataset(env: ObjectRearrangementEnv, windows: TensorDict) -> None:
    torch.manual_seed(0)
    palette = palette_from_frames(windows["pixels"])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
    loss = VideoPredictionLoss(model, open_loop_length=1)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = windows[:16]
    first = float(loss(batch)["loss_reconstruction"].detach())
    for _ in range(60):
        out = loss(batch)
        optimizer.zero_grad()
        (out["loss_reconstruction"] + out["loss_kl"]).backward()
        optimizer.step()
    last = loss(batch)
    assert float(last["loss_reconstruction"].detach()) < 0.5 * first
    assert float(last["pixel_accuracy"]) > 0.95


# ------------------------------------------------------------------ metrics
def test_open_loop_accuracy_matches_a_manual_count(
    model: VideoPredictionModel, windows: TensorDict
) -> None:
    result = open_loop_accuracy(model, windows, chunk_size=10)
    frames = model.rollout(windows[:, 0]["pixels"], windows["action"])
    exact = (frames == windows["next", "pixels"]).flatten(2).all(-1).float().mean(0)
    assert result["horizon"] == 4 and result["num_sequences"] == 64
    assert torch.allclose(torch.tensor(result["exact_accuracy"]), exact)
    assert result["exact_accuracy_last"] == pytest.approx(float(exact[-1]))
    # The untrained model copies its first frame at every step: it is exact (zero error)
    # where the true frame has not changed, and its mean squared error on values in [0, 1]
    # is that of the first frame against the truth.
    first = windows[:, 0]["pixels"]
    assert torch.equal(frames, first[:, None].expand_as(frames))
    truth = windows["next", "pixels"]
    unchanged = (truth == first[:, None]).flatten(2).all(-1).float().mean(0)
    assert torch.equal(exact, unchanged) and 0 < float(unchanged[0]) < 1
    error = ((first[:, None].double() - truth.double()) / 255).pow(2).flatten(2).mean(-1)
    assert torch.allclose(torch.tensor(result["pixel_mse"], dtype=torch.float64), error.mean(0))
    assert (error[(truth == first[:, None]).flatten(2).all(-1)] == 0).all()
    with pytest.raises(ValueError, match=r"\[N, H\]"):
        open_loop_accuracy(model, windows[:, 0])


# ------------------------------------------------------------------ trainer
def test_trainer_schedules_and_evaluation(tmp_path) -> None:
    trainer = WorldModelTrainer(tiny_config(tmp_path, num_steps=10, open_loop_ramp=0.5))
    assert trainer.open_loop_length_at(0) == 1
    assert trainer.open_loop_length_at(5) == 3  # ramp ends at half of 10 steps
    assert trainer.lr_at(0) == pytest.approx(2e-3) and trainer.lr_at(10) == pytest.approx(1e-4)
    result = trainer.train()
    assert result["step"] == 10
    assert len(result["evaluation"]["exact_accuracy"]) == 3
    # eval_every=3: evaluations at steps 3, 6 and 9, and one at the end
    assert [row["step"] for row in trainer.evaluations] == [3, 6, 9, 10]
    assert (
        trainer.evaluations[-1]["exact_accuracy_last"]
        == result["evaluation"]["exact_accuracy_last"]
    )
    assert (tmp_path / "wm" / "checkpoints" / "last.pt").exists()
    assert (tmp_path / "wm" / "logs").exists()


def test_resume_equals_uninterrupted_run(tmp_path) -> None:
    full = WorldModelTrainer(tiny_config(tmp_path / "a"))
    full.train()
    first = WorldModelTrainer(tiny_config(tmp_path / "b", num_steps=6))
    # interrupted after the checkpoint at step 3
    while first.step < 3:
        first.train_step()
    first.save()
    resumed = WorldModelTrainer(tiny_config(tmp_path / "b"))
    with mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step:
        result = resumed.train(resume=True)
    # It went on from the checkpoint: step 3 reported, only steps 4-6 trained here.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 3
    assert step.call_count == 3 and resumed.step == result["step"] == 6
    for name, value in full.model.state_dict().items():
        assert torch.equal(value, resumed.model.state_dict()[name]), name
    # Evaluations (eval_every=3) at 3 and 6 in both runs; the resumed one only made the one at 6.
    assert [row["step"] for row in full.evaluations] == [3, 6]
    assert [row["step"] for row in resumed.evaluations] == [6]


def test_checkpoint_round_trip_and_clear_errors(tmp_path) -> None:
    trainer = WorldModelTrainer(tiny_config(tmp_path, num_steps=3))
    trainer.train()
    path = trainer.checkpoint_path
    other = WorldModelTrainer(tiny_config(tmp_path / "copy", num_steps=3))
    other.load(path)
    assert other.step == 3
    for name, value in trainer.model.state_dict().items():
        assert torch.equal(value, other.model.state_dict()[name])
    loaded = load_video_model(path, env=trainer.env)
    assert not loaded.training
    pixels = trainer.eval_windows[:, 0]["pixels"]
    action = trainer.eval_windows[:, 0]["action"]
    assert torch.equal(loaded.predict(pixels, action), trainer.model.predict(pixels, action))
    with pytest.raises(ValueError, match="another environment"):
        load_video_model(path, env=ObjectRearrangementEnv(num_objects=2))
    with pytest.raises(ValueError, match="'world_model'"):
        load_encoder(path)
    two_objects = WorldModelTrainer(tiny_config(tmp_path / "two", num_objects=2))
    with pytest.raises(ValueError, match="another environment"):
        two_objects.load(path)
    bigger = WorldModelTrainer(tiny_config(tmp_path / "big", model=VideoModelConfig.default()))
    with pytest.raises(ValueError, match="video model"):
        bigger.load(path)
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupted"):
        other.load(broken)


def test_config_validation_names_the_field(tmp_path) -> None:
    with pytest.raises(ValueError, match="trajectory_length"):
        WorldModelTrainer(tiny_config(tmp_path, trajectory_length=2))
    with pytest.raises(ValueError, match="feedback"):
        tiny_config(tmp_path, feedback="teacher").validate()
    with pytest.raises(ValueError, match="unknown WorldModelConfig fields"):
        WorldModelConfig.from_dict({"num_stepz": 3})
    cfg = tiny_config(tmp_path)
    assert WorldModelConfig.from_dict(cfg.to_dict()) == cfg


def test_event_share_validation_names_the_field(tmp_path) -> None:
    for bad in (-0.1, 1.0, 2, "some"):
        with pytest.raises(ValueError, match=r"event_share .*\[0, 1\)|event_share"):
            tiny_config(tmp_path, event_share=bad)
    with pytest.raises(ValueError, match="event windows only"):
        tiny_config(tmp_path, event_share=1.0)
    assert tiny_config(tmp_path, event_share=0.25).event_share == 0.25
    # key-wall trains with event windows, the other presets with uniform ones
    assert WorldModelConfig.for_env("key-wall").event_share == 0.25
    assert WorldModelConfig.for_env("rearrangement", 3).event_share == 0.0
    assert WorldModelConfig.for_env("key-corridor").event_share == 0.0


def test_configs_and_checkpoints_without_event_share_load(tmp_path) -> None:
    """Stored before the field existed: read as 0, the uniform windows they were trained on."""
    old = tiny_config(tmp_path).to_dict()
    del old["event_share"]
    assert WorldModelConfig.from_dict(old).event_share == 0.0
    flat = {k: v for k, v in WorldModelConfig.for_env("key-wall").to_dict().items() if k != "model"}
    del flat["event_share"]
    flat.update(model_preset="small", latent_dim=4, prior="fixed")  # an older flat config
    assert WorldModelConfig.from_dict(flat).event_share == 0.0
    trainer = WorldModelTrainer(tiny_config(tmp_path, num_steps=2))
    trainer.train()
    payload = load_checkpoint(trainer.checkpoint_path)
    payload["config"].pop("event_share")
    path = save_checkpoint(
        tmp_path / "old.pt", **{k: payload[k] for k in ("kind", "config", "env_config", "state")},
        step=payload["step"], rng=payload["rng"], extra=payload["extra"],
    )  # fmt: skip
    model = load_video_model(path, env=trainer.env)
    frames, actions = trainer.eval_windows[:, 0]["pixels"], trainer.eval_windows[:, 0]["action"]
    assert torch.equal(model.predict(frames, actions), trainer.model.predict(frames, actions))
    resumed = WorldModelTrainer(tiny_config(tmp_path / "resumed", num_steps=2))
    resumed.load(path)
    assert resumed.step == 2


def test_trainer_with_event_share_samples_and_evaluates_event_windows(tmp_path) -> None:
    env = KeyWallEnv(batch_size=(4,), seed=0)
    cfg = WorldModelConfig.for_env("key-wall",
        num_steps=2, num_frames=4000, num_envs=4, horizon=4, eval_frames=2000,
        eval_sequences=16, batch_size=64,
        model=VideoModelConfig.small(), eval_every=10**6, progress=False,
        out_dir=str(tmp_path / "wm"),
    )  # fmt: skip
    # seeded walks of 1000 steps that take the key 4 times (training) and 3 times (held out)
    buffer = collect_play_data(env, 4000, seed=0)
    held_out = collect_play_data(env, 2000, seed=2)
    trainer = WorldModelTrainer(cfg, buffer=buffer, eval_buffer=held_out)
    assert isinstance(trainer.buffer.sampler, EventWindowSampler)
    assert not isinstance(held_out.sampler, EventWindowSampler)  # held-out windows stay uniform
    batch = trainer.buffer.sample(64)
    key_taken = (batch["next", "state"][..., 2] != batch["state"][..., 2]).any(-1)
    assert key_taken.float().mean() >= 0.1  # about 0.25 (uniform: about 0.004)
    windows = trainer.eval_event_windows
    assert windows is not None and windows.shape == (12, 4)  # 3 events x 4 windows each
    assert (windows["next", "state"][..., 2] != windows["state"][..., 2]).any(-1).all()
    evaluation = trainer.train()["evaluation"]
    assert evaluation["event_num_sequences"] == 12
    # The event accuracies are the trained model's exact frames on those windows, by step.
    frames = trainer.model.eval().rollout(windows[:, 0]["pixels"], windows["action"])
    exact = (frames == windows["next", "pixels"]).flatten(2).all(-1).double().mean(0)
    for h in (1, 2, 4):
        assert evaluation[f"event_exact_accuracy_step{h}"] == pytest.approx(float(exact[h - 1]))
    uniform = WorldModelTrainer(cfg.replace(event_share=0.0, out_dir=str(tmp_path / "u")))
    assert type(uniform.buffer.sampler) is SequenceSampler and uniform.eval_event_windows is None


def test_the_video_model_plugs_into_a_planning_env_and_planner(
    env: ObjectRearrangementEnv, model: VideoPredictionModel
) -> None:
    from dorp_rl.envs import VideoModelEnv
    from dorp_rl.planners import PixelDistanceCost, RandomShootingPlanner

    planning_env = VideoModelEnv(model, env.num_actions)
    planner = RandomShootingPlanner(
        planning_env, PixelDistanceCost(), planning_horizon=3, num_candidates=16, seed=0
    )
    td = env.reset()
    action = planner(td.clone())["action"]
    assert action.shape == (16, 1) and action.dtype == torch.int64
    assert bool(env.action_spec.is_in(action))
    # the imagined frames are the model's own rollout
    rollout = planner.imagine(td[:2].clone(), torch.zeros(2, 1, 3, dtype=torch.int64))
    expected = model.rollout(td[:2]["pixels"], torch.zeros(2, 3, 1, dtype=torch.int64))
    assert torch.equal(rollout["next", "pixels"].reshape(2, 3, 3, 16, 16), expected)
