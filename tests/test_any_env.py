"""Play data, codes and code graphs of an env written here, not one of the project's.

``PushBlocksEnv`` has two blocks of different shapes and shades on a canvas of any
``(C, H, W)``; an action moves one block one cell. Its frames are 3 x 24 x 32 or 1 x 8 x 8,
its actions ``Categorical`` or ``OneHot``: nothing in it is what the project's envs have.
"""

from __future__ import annotations

import importlib.machinery
import sys
import types

import pytest
import torch
from push_blocks import MOVES, PushBlocksEnv  # noqa: F401  (MOVES for readers)
from tensordict import TensorDict
from torchrl.data import Bounded, Composite
from torchrl.envs import Compose

from dorp_rl.data import (
    FuturePairSampler,
    UniformRandomPolicy,
    check_play_buffer,
    collect_play_data,
    future_pairs,
    load_play_data,
    play_env,
)
from dorp_rl.envs import DiscreteActions, env_identity
from dorp_rl.envs.spec import qualified_name
from dorp_rl.eval import play_code_dynamics
from dorp_rl.frames import frame_shape_of
from dorp_rl.modules import DDDPSimilarity, DiscreteCodeEncoder, EncoderConfig
from dorp_rl.objectives import CPCLoss
from dorp_rl.planners import CodeGraph
from dorp_rl.planners.play_codes import play_actions


@pytest.mark.parametrize(
    "frame_shape, one_hot", [((3, 24, 32), False), ((1, 8, 8), True)], ids=["3x24x32", "1x8x8"]
)
def test_play_data_codes_and_graph_of_an_env_of_another_frame_size(frame_shape, one_hot, tmp_path):
    env = PushBlocksEnv(frame_shape, batch_size=(4,), one_hot=one_hot)
    assert frame_shape_of(env) == frame_shape
    actions = DiscreteActions.of(env)
    assert (actions.num_actions, actions.one_hot) == (8, one_hot)

    buffer = collect_play_data(
        env, 400, directory=tmp_path / "play", seed=0, trajectory_length=10, progress=False
    )
    assert len(buffer) == 400
    sample = buffer[:400]
    assert tuple(sample["pixels"].shape) == (400, *frame_shape)
    assert tuple(sample["action"].shape) == ((400, 8) if one_hot else (400, 1))
    # Trajectories of 10 steps: step_count runs 0..9 within each traj_id.
    assert int(sample["step_count"].max()) == 9 and len(sample["traj_id"].unique()) == 40
    # Each transition's next frame is the env's step from its state and action.
    probe = PushBlocksEnv(frame_shape, batch_size=(1,), one_hot=one_hot)
    for i in (0, 17, 399):
        step = probe._step(
            TensorDict(
                state=sample["state"][i : i + 1],
                goal_state=sample["state"][i : i + 1],
                goal_pixels=sample["pixels"][i : i + 1],
                action=sample["action"][i : i + 1],
                batch_size=[1],
            )
        )
        assert torch.equal(step["pixels"][0], sample["next", "pixels"][i])
    # Same seed, same data; the stored collection is loaded, not collected again.
    again = load_play_data(tmp_path / "play")
    assert torch.equal(again[:400]["pixels"], sample["pixels"])
    assert buffer.metadata["env_config"] == env_identity(env)

    torch.manual_seed(0)
    encoder = DiscreteCodeEncoder.for_env(
        env, EncoderConfig.small((6, 6), channels=8, mlp_sizes=(32,))
    )
    assert encoder.frame_shape == frame_shape
    pairs = load_play_data(tmp_path / "play", sampler=FuturePairSampler(1, 2), batch_size=32)
    loss = CPCLoss(encoder, DDDPSimilarity(12), exclusivity_weight=1.0)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        anchor, future, _ = future_pairs(pairs.sample())
        out = loss(TensorDict(pixels=anchor, future_pixels=future, batch_size=[32]))
        optim.zero_grad()
        out["loss_cpc"].backward()
        optim.step()
        losses.append(float(out["loss_cpc"].detach()))
    assert sum(losses[-5:]) / 5 < sum(losses[:5]) / 5  # the codes learn something

    dynamics = play_code_dynamics(buffer, encoder)
    assert len(dynamics["dead"]) == 2 and all(0.0 <= r <= 1.0 for r in dynamics["change_rate"])

    graph = CodeGraph.from_play_data(buffer, encoder, num_actions=8)
    assert graph.num_groups == 2 and graph.num_nodes(0) >= 1
    assert graph.action_counts is not None and graph.action_counts.shape[-1] == 8
    # One-hot actions are read by their hot entry, not dropped.
    assert torch.equal(play_actions(buffer), actions.index(sample["action"]).squeeze(-1))


def test_another_envs_play_data_and_frames_are_refused(tmp_path):
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    buffer = collect_play_data(env, 40, seed=0, trajectory_length=5)
    other = PushBlocksEnv((1, 8, 8), batch_size=(4,))
    with pytest.raises(ValueError, match="another environment"):
        check_play_buffer(buffer, other)
    check_play_buffer(buffer, PushBlocksEnv((3, 24, 32), batch_size=(4,)))
    encoder = DiscreteCodeEncoder.for_env(other, EncoderConfig.small((4,)))
    with pytest.raises(ValueError, match=r"pixels must have shape \[\*B, 1, 8, 8\]"):
        encoder(buffer[:2]["pixels"])


def test_an_env_run_as_a_script_has_the_identity_it_has_when_imported(monkeypatch):
    # `python push_blocks.py` defines the env in `__main__`; its checkpoints must fit
    # the same env imported as `push_blocks` (e.g. `dorp evaluate --env push_blocks:...`).
    imported = env_identity(PushBlocksEnv((1, 8, 8), batch_size=(2,)))
    assert imported["env"] == "push_blocks.PushBlocksEnv"

    class AsScript(PushBlocksEnv):
        pass

    AsScript.__module__, AsScript.__qualname__ = "__main__", "PushBlocksEnv"
    script = types.ModuleType("__main__")
    script.__file__, script.__spec__ = "/somewhere/push_blocks.py", None
    monkeypatch.setitem(sys.modules, "__main__", script)
    assert env_identity(AsScript((1, 8, 8), batch_size=(2,))) == imported
    script.__spec__ = importlib.machinery.ModuleSpec("tests.push_blocks", None)  # python -m
    assert qualified_name(AsScript) == "tests.push_blocks.PushBlocksEnv"


def test_play_needs_what_it_cannot_guess():
    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    with pytest.raises(ValueError, match="trajectory_length is needed for PushBlocksEnv"):
        play_env(env)
    unbatched = PushBlocksEnv((3, 24, 32), batch_size=())
    with pytest.raises(ValueError, match="one batch dimension"):
        play_env(unbatched, 5)
    continuous = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    continuous.action_spec = Bounded(-1.0, 1.0, (4, 2))
    with pytest.raises(ValueError, match="must be discrete"):
        play_env(continuous, 5)
    renamed = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    renamed.observation_spec = Composite(
        image=renamed.observation_spec["pixels"].clone(), shape=renamed.batch_size
    )
    with pytest.raises(
        ValueError, match=r"no image observation 'pixels'; its observations are \['image'\]"
    ):
        play_env(renamed, 5)


def test_the_random_policy_draws_the_envs_own_action_layout():
    env = PushBlocksEnv((1, 8, 8), batch_size=(5,), one_hot=True)
    policy = UniformRandomPolicy.for_env(env, seed=3)
    action = policy(env.reset())["action"]
    assert action.shape == (5, 8) and bool((action.sum(-1) == 1).all())
    assert env.action_spec.is_in(action)
    again = UniformRandomPolicy.for_env(env, seed=3)(env.reset())["action"]
    assert torch.equal(action, again)


def test_label_free_code_dynamics_of_play_data():
    """Play of 6-step walks: one-hot 0 follows a cell that moves, one-hot 1 is a two-code
    one-hot that never changes (dead), one-hot 2 flips and flips back at once."""
    from dorp_rl.eval import code_dynamics

    steps = torch.arange(6)
    walk = torch.tensor([0, 1, 2, 3, 4, 5, 6])  # a code per step, never back
    flip = torch.tensor([0, 1, 0, 0, 0, 0, 0])  # changed at step 0, undone at step 1
    codes = torch.stack([walk[:-1], torch.ones(6, dtype=torch.long), flip[:-1]], -1)
    next_codes = torch.stack([walk[1:], torch.ones(6, dtype=torch.long), flip[1:]], -1)
    two = code_dynamics(
        torch.cat([codes, codes]),
        torch.cat([next_codes, next_codes]),
        torch.tensor([0] * 6 + [1] * 6),
        torch.cat([steps, steps]),
        window=2,
    )
    assert two["codes_used"] == [7, 1, 2]
    assert two["change_rate"][0] == 1.0 and two["change_rate"][2] == pytest.approx(2 / 6)
    assert two["dead"] == [False, True, False]
    assert two["undo_rate"][0] == 0.0 and two["undo_rate"][1] is None
    assert two["undo_rate"][2] == 0.5  # the flip at step 0 is undone, its undo is not
    # Shuffled transitions give the same answer: order comes from traj_id and step_count.
    perm = torch.randperm(12, generator=torch.Generator().manual_seed(0))
    shuffled = code_dynamics(
        torch.cat([codes, codes])[perm],
        torch.cat([next_codes, next_codes])[perm],
        torch.tensor([0] * 6 + [1] * 6)[perm],
        torch.cat([steps, steps])[perm],
        window=2,
    )
    assert shuffled == two
    # Without trajectories, no undo rates; a broken layout is named.
    assert code_dynamics(codes, next_codes)["undo_rate"] == [None, None, None]
    with pytest.raises(ValueError, match="traj_id and step_count go together"):
        code_dynamics(codes, next_codes, torch.zeros(6))


def test_gray_frames_of_any_size_are_drawn_in_three_equal_channels(tmp_path):
    from dorp_rl.viz import frames_to_rgb_array, save_frame_strip

    env = PushBlocksEnv((1, 8, 8), batch_size=(3,))
    frames = env.reset()["pixels"]
    rgb = frames_to_rgb_array(frames, scale=2)
    assert rgb.shape == (3, 16, 16, 3)
    assert (rgb[..., 0] == rgb[..., 2]).all() and rgb.max() > 0
    assert save_frame_strip(frames, tmp_path / "gray.png").exists()
    with pytest.raises(ValueError, match=r"\(RGB\) or \[\.\.\., 1, H, W\] \(gray\)"):
        frames_to_rgb_array(torch.zeros(2, 2, 8, 8, dtype=torch.uint8))


def test_one_name_and_one_factory_for_the_low_level():
    from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
    from dorp_rl.policies import TRUE_DYNAMICS, make_planning_env

    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    assert TRUE_DYNAMICS == "gt"
    planning = make_planning_env(env, "gt")
    assert isinstance(planning, GroundTruthModelEnv)
    assert make_planning_env(env, planning) is planning
    with pytest.raises(ValueError, match="the true dynamics are spelled 'gt'"):
        make_planning_env(env, "ground_truth")
    with pytest.raises(ValueError, match="got int"):
        make_planning_env(env, 3)


class BlockRegionEncoder(torch.nn.Module):
    """Codes of PushBlocksEnv frames read off their pixels: per block, the region of
    ``cell x cell`` pixels holding its top-left cell (an encoder written for this env)."""

    def __init__(self, env: PushBlocksEnv, cell: int = 4) -> None:
        super().__init__()
        _, h, w = env.frame_shape
        self.cell, self.cols = cell, -(-w // cell)
        regions = -(-h // cell) * self.cols
        self.code_sizes = (regions, regions)
        self.register_buffer("shades", env.shades.clone())

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codes = []
        for shade in self.shades:
            mask = (pixels == shade.view(-1, 1, 1)).all(-3)  # [*B, H, W]
            row = mask.any(-1).to(torch.int64).argmax(-1)
            col = mask.any(-2).to(torch.int64).argmax(-1)
            codes.append((row // self.cell) * self.cols + col // self.cell)
        code = torch.stack(codes, -1)
        return code, torch.nn.functional.one_hot(code, self.code_sizes[0]).float()

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor) -> torch.Tensor:
        return self(torch.as_tensor(pixels))[0]


def test_dorp_with_the_true_dynamics_of_an_env_written_here():
    """Play data, a code graph and the DORP policy on 3 x 24 x 32 frames; the planning
    env is the env itself, stepped at any leading shape (its true dynamics)."""
    from dorp_rl.policies import make_dorp_policy

    play = PushBlocksEnv((3, 24, 32), batch_size=(8,), seed=1)
    buffer = collect_play_data(play, 4000, seed=0, trajectory_length=50)
    encoder = BlockRegionEncoder(play)
    graph = CodeGraph.from_play_data(buffer, encoder, num_actions=8)
    assert graph.num_nodes(0) >= 40 and graph.env_config == env_identity(play)

    env = PushBlocksEnv((3, 24, 32), batch_size=(4,), seed=2)
    model = PushBlocksEnv((3, 24, 32), batch_size=(), batch_locked=False)
    policy = make_dorp_policy(
        env, encoder, graph, low_level=model, seed=0, num_candidates=200, planning_horizon=8
    )
    start = torch.tensor(
        [[[0, 0], [20, 30]], [[5, 5], [10, 10]], [[22, 0], [0, 31]], [[3, 20], [15, 2]]]
    )
    goal = torch.tensor(
        [[[12, 20], [2, 3]], [[20, 25], [1, 28]], [[0, 28], [20, 5]], [[3, 22], [15, 0]]]
    )
    td = env.reset(TensorDict(state=start, goal_state=goal, batch_size=[4]), set_state=True)
    rollout = env.rollout(300, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    solved = rollout["next", "done"].squeeze(-1).any(-1)
    assert solved.all(), rollout["dorp_mode"][:, -1]
    steps = rollout["next", "done"].squeeze(-1).float().argmax(-1) + 1
    bound = (start - goal).abs().sum((-1, -2))
    assert (steps <= 3 * bound).all(), (steps, bound)

    other = PushBlocksEnv((1, 8, 8), batch_size=(4,))
    with pytest.raises(ValueError, match="another environment's play data"):
        make_dorp_policy(other, encoder, graph, low_level=model, seed=0)


def test_ground_truth_parts_need_what_the_env_declares(tmp_path):
    """Oracle codes and ground-truth diagnostics come from hooks an env or its profile
    declares, not from its class: an env without them is refused with a message saying
    what is missing."""
    from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
    from dorp_rl.viz import write_diagnostic_plots

    env = PushBlocksEnv((3, 16, 16), batch_size=(2,))
    with pytest.raises(ValueError, match=r"env must declare oracle_layout\(\)"):
        OracleCodeEncoder(env)
    with pytest.raises(ValueError, match="PushBlocksEnv's profile declares no code diagnostics"):
        write_diagnostic_plots(env, lambda pixels: pixels, tmp_path)
    assert OracleCodeEncoder(ObjectRearrangementEnv(num_objects=3)).code_sizes == (16, 16, 16)
    assert OracleCodeEncoder(KeyWallEnv()).code_sizes == (16, 2)


def test_the_true_dynamics_of_a_batch_locked_one_hot_env_step_any_shape():
    """make_planning_env(env, 'gt') over an env fixed at batch (4,) with one-hot actions:
    [3, 5] candidates step in chunks of 4, with index actions, as the env itself would."""
    from dorp_rl.envs.planning import StatelessEnvModel
    from dorp_rl.policies import make_planning_env

    env = PushBlocksEnv((1, 8, 8), batch_size=(4,), one_hot=True, seed=3)
    model = make_planning_env(env, "gt")
    assert isinstance(model, StatelessEnvModel) and model.action_spec.shape == (1,)
    start = env.reset()
    td = start[:3].unsqueeze(1).expand(3, 5).clone()
    td["action"] = torch.randint(0, 8, (3, 5, 1), generator=torch.Generator().manual_seed(0))
    out = model.step(td)["next"]
    assert out["pixels"].shape == (3, 5, 1, 8, 8) and not bool(out["done"].any())
    free = PushBlocksEnv((1, 8, 8), batch_size=(), one_hot=True, batch_locked=False)
    for i, j in ((0, 0), (1, 3), (2, 4)):
        one = td[i, j].clone()
        one["action"] = torch.nn.functional.one_hot(one["action"].squeeze(-1), 8)
        assert torch.equal(free._step(one)["state"], out["state"][i, j])
    # Set states come back as given, in any leading shape.
    reset = model.reset(td.select("state", "goal_state"), set_state=True)
    assert torch.equal(reset["state"], td["state"])
    # An env without a settable state cannot be its own true dynamics.
    env._supports_set_state = False
    with pytest.raises(ValueError, match="cannot serve as its own true dynamics"):
        StatelessEnvModel(env)


def test_a_profile_is_found_by_name_import_path_or_env(tmp_path):
    from dorp_rl.envs import (
        EnvProfile,
        ObjectRearrangementEnv,
        env_profile,
        profile_of,
        register_env_profile,
    )
    from dorp_rl.trainers import RepresentationConfig

    profile = env_profile("push_blocks:PUSH_BLOCKS")
    assert profile.name == "push-blocks" and profile.play_trajectory_length == 20
    # Once imported, a profile is known by its name (what a checkpoint trained on it says).
    assert env_profile("push-blocks") is profile
    bare = env_profile("push_blocks:make_small_env")
    # a bare factory leaves the play length to be chosen from the env's resets
    assert bare.name == "push_blocks:make_small_env" and bare.play_trajectory_length is None
    env = bare.build(batch_size=(2,), seed=0)
    assert tuple(env.batch_size) == (2,)
    assert profile_of(ObjectRearrangementEnv(num_objects=2)).name == "rearrangement"
    assert profile_of(env) is None
    # Configs keep the name they were given, so they resolve again after a reload.
    cfg = RepresentationConfig.for_env("push_blocks:PUSH_BLOCKS")
    assert cfg.env == "push_blocks:PUSH_BLOCKS" and cfg.code_sizes == (6, 6)
    assert RepresentationConfig.from_dict(cfg.to_dict()).code_sizes == (6, 6)
    with pytest.raises(ValueError, match="applies to envs that count objects"):
        RepresentationConfig.for_env("push_blocks:PUSH_BLOCKS", num_objects=3)
    mine = EnvProfile(name="test-mine", make_env=lambda **_: PushBlocksEnv((3, 8, 8)))
    register_env_profile(mine)
    try:
        assert env_profile("test-mine") is mine
        with pytest.raises(ValueError, match="already registered"):
            register_env_profile(EnvProfile(name="test-mine", make_env=lambda **_: None))
    finally:
        from dorp_rl.envs import profile as profiles

        del profiles._REGISTRY["test-mine"]
    # Once unknown again (a fresh process loading a checkpoint trained on it), the error
    # says how to make a profile made in code known by its name.
    with pytest.raises(ValueError, match=r"call register_env_profile\(profile\)"):
        env_profile("test-mine")
    with pytest.raises(ValueError, match="must return a TorchRL EnvBase"):
        EnvProfile(name="bad", make_env=lambda **_: 3).build()


class _Dots:
    """A gymnasium env written here whose image is an observation (``{"image": H x W x 3}``),
    not its renderer: a dot on a 10 x 12 canvas, moved by 4 actions."""

    def __new__(cls):
        import gymnasium as gym
        import numpy as np

        class Dots(gym.Env):
            observation_space = gym.spaces.Dict(
                {"image": gym.spaces.Box(0, 255, (10, 12, 3), np.uint8)}
            )
            action_space = gym.spaces.Discrete(4)

            def _obs(self):
                image = np.zeros((10, 12, 3), np.uint8)
                image[self.pos[0], self.pos[1]] = (250, 120, 30)
                return {"image": image}

            def reset(self, *, seed=None, options=None):
                super().reset(seed=seed)
                self.pos = [int(v) for v in self.np_random.integers(0, (10, 12))]
                return self._obs(), {}

            def step(self, action):
                dr, dc = ((-1, 0), (1, 0), (0, -1), (0, 1))[int(action)]
                self.pos = [min(max(self.pos[0] + dr, 0), 9), min(max(self.pos[1] + dc, 0), 11)]
                return self._obs(), 0.0, False, False, {}

        return Dots()


def test_a_gymnasium_env_with_an_image_observation_through_gym_wrapper_and_a_rename():
    """An image named otherwise than ``pixels`` is mapped by torchrl's RenameTransform
    (and laid out [C, H, W] by PermuteTransform); then play data, an encoder sized from
    its frames and a code graph."""
    from torchrl.envs import (
        GymWrapper,
        PermuteTransform,
        RenameTransform,
        SerialEnv,
        TransformedEnv,
    )

    def one():
        env = GymWrapper(_Dots())
        return TransformedEnv(
            env,
            Compose(
                RenameTransform(["image"], ["pixels"]),
                PermuteTransform((-1, -3, -2), in_keys=["pixels"]),
            ),
        )

    env = SerialEnv(3, one)
    env.set_seed(0)
    assert frame_shape_of(env) == (3, 10, 12)
    buffer = collect_play_data(env, 300, trajectory_length=20, seed=0)
    pixels = buffer[:300]["pixels"]
    assert pixels.shape == (300, 3, 10, 12) and pixels.dtype == torch.uint8
    # One lit cell per frame: the renamed image is the env's observation.
    assert bool(((pixels.sum(1) > 0).flatten(1).sum(-1) == 1).all())
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8,), frame_shape=(3, 10, 12)))
    graph = CodeGraph.from_play_data(buffer, encoder)
    assert graph.num_nodes(0) >= 1


def test_an_env_s_own_diagnostics_come_through_its_profile(tmp_path):
    """An env written here declares diagnostics of its own (EnvProfile.diagnostics): the
    code trainer logs them beside the label diagnostics of ``objects``, and the pictures
    and the rollout GIFs' code maps come from them; an env class alone has none."""
    from tiny_args import tiny_codes

    from dorp_rl.envs import env_profile
    from dorp_rl.trainers import RepresentationTrainer
    from dorp_rl.viz import code_maps_for_waypoints, write_diagnostic_plots

    cfg = tiny_codes(
        "push_blocks:PUSH_BLOCKS_DIAGNOSED", tmp_path, num_frames=256, num_steps=3,
        diagnostics_samples=64, encoder={},
    )  # fmt: skip
    trainer = RepresentationTrainer(cfg)
    trainer.train()
    result = trainer.evaluate()
    assert len(result["block_purity"]) == 2 and all(0 < p <= 1 for p in result["block_purity"])
    assert "purity" in result["objects"]  # the labels of the profile's objects, as before
    profile = env_profile("push_blocks:PUSH_BLOCKS_DIAGNOSED")
    env = profile.build(batch_size=(4,))
    files = write_diagnostic_plots(
        env, trainer.encoder.encode, tmp_path / "pictures", profile=profile
    )
    assert files["code_map"].read_bytes().startswith(b"\x89PNG")
    measured = profile.diagnostics.measure(env, trainer.encoder.encode, 64, 0)
    maps = code_maps_for_waypoints(profile.diagnostics.waypoint_maps(env, None, measured), 2)
    assert [m[0].shape for m in maps] == [(24, 32), (24, 32)]
    with pytest.raises(ValueError, match="profile declares no code diagnostics"):
        write_diagnostic_plots(env, trainer.encoder.encode, tmp_path)  # no registered profile
