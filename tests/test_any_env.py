"""Play data, codes and code graphs of an env written here, not one of the project's.

``PushBlocksEnv`` has two blocks of different shapes and shades on a canvas of any
``(C, H, W)``; an action moves one block one cell. Its frames are 3 x 24 x 32 or 1 x 8 x 8,
its actions ``Categorical`` or ``OneHot``: nothing in it is what the project's envs have.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

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
from dorp_rl.eval import play_code_dynamics
from dorp_rl.modules import DDDPSimilarity, DiscreteCodeEncoder, EncoderConfig
from dorp_rl.objectives import CPCLoss
from dorp_rl.planners import CodeGraph
from dorp_rl.planners.code_graph import play_actions
from dorp_rl.validation import frame_shape_of

MOVES = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]])


class PushBlocksEnv(EnvBase):
    """Two blocks on an ``H x W`` canvas; action ``4 * block + direction`` moves one block.

    Block 0 is 1 x 2 cells, block 1 is 2 x 1; their shades differ in every channel. The
    state is the blocks' top-left cells, int64 ``[2, 2]``.
    """

    def __init__(self, frame_shape=(3, 24, 32), batch_size=(4,), one_hot=False, seed=0):
        super().__init__(batch_size=torch.Size(batch_size))
        self.frame_shape = tuple(frame_shape)
        c, h, w = self.frame_shape
        self.sizes = torch.tensor([[1, 2], [2, 1]])
        self.shades = torch.tensor([[250, 120, 40], [60, 200, 160]], dtype=torch.uint8)[:, :c]
        if c > 3:
            raise ValueError("at most 3 channels in this test env")
        b = self.batch_size
        self.observation_spec = Composite(
            pixels=Bounded(0, 255, (*b, c, h, w), dtype=torch.uint8),
            state=Unbounded((*b, 2, 2), dtype=torch.int64),
            shape=b,
        )
        if one_hot:
            self.action_spec = OneHot(8, shape=(*b, 8))
        else:
            self.action_spec = Categorical(8, shape=(*b, 1))
        self.reward_spec = Unbounded((*b, 1))
        self.rng = torch.Generator()
        self.set_seed(seed)

    def _set_seed(self, seed):
        self.rng.manual_seed(int(seed) if seed is not None else 0)

    def render_state(self, state):
        c, h, w = self.frame_shape
        frames = torch.zeros(*state.shape[:-2], c, h, w, dtype=torch.uint8)
        flat, cells = frames.reshape(-1, c, h, w), state.reshape(-1, 2, 2)
        for i in range(flat.shape[0]):
            for block in range(2):
                (r, col), (dh, dw) = cells[i, block].tolist(), self.sizes[block].tolist()
                flat[i, :, r : r + dh, col : col + dw] = self.shades[block].view(c, 1, 1)
        return frames

    def _limits(self):
        _, h, w = self.frame_shape
        return torch.tensor([h, w]) - self.sizes  # highest top-left cell per block

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        high = self._limits() + 1
        state = (torch.rand(*self.batch_size, 2, 2, generator=self.rng) * high).long()
        return TensorDict(pixels=self.render_state(state), state=state, batch_size=self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = DiscreteActions.of(self).index(tensordict["action"]).squeeze(-1)
        state = tensordict["state"].clone()
        block, move = action // 4, MOVES[action % 4]
        rows = torch.arange(state.shape[0])
        moved = state[rows, block] + move
        state[rows, block] = torch.minimum(moved.clamp(min=0), self._limits()[block])
        return TensorDict(
            pixels=self.render_state(state),
            state=state,
            reward=torch.zeros(*self.batch_size, 1),
            done=torch.zeros(*self.batch_size, 1, dtype=torch.bool),
            terminated=torch.zeros(*self.batch_size, 1, dtype=torch.bool),
            batch_size=self.batch_size,
        )


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
                state=sample["state"][i : i + 1], action=sample["action"][i : i + 1], batch_size=[1]
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
