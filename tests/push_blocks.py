"""PushBlocksEnv: an env written for the tests, not one of the project's, and its profile.

Two blocks of different shapes and shades on a canvas of any ``(C, H, W)``; an action
moves one block one cell. Importable as ``push_blocks`` (the tests folder is on the
path), so the ``dorp`` command can take it as ``--env push_blocks:PUSH_BLOCKS`` or
``--env push_blocks:make_env``.
"""

from __future__ import annotations

import dataclasses

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.envs import CodeDiagnostics, DiscreteActions, EnvProfile

MOVES = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]])


class PushBlocksEnv(EnvBase):
    """Two blocks on an ``H x W`` canvas; action ``4 * block + direction`` moves one block.

    Block 0 is 1 x 2 cells, block 1 is 2 x 1; their shades differ in every channel. The
    state is the blocks' top-left cells, int64 ``[2, 2]``; a task is solved when it equals
    ``goal_state``. Stateless: a step reads the state from the tensordict, so with
    ``batch_size=()`` and ``batch_locked=False`` it steps any leading shape (its own true
    dynamics as a planning env), and ``reset(td, set_state=True)`` starts from given states.
    """

    _supports_set_state = True

    def __init__(
        self, frame_shape=(3, 24, 32), batch_size=(4,), one_hot=False, seed=0, batch_locked=True
    ):
        super().__init__(batch_size=torch.Size(batch_size))
        self.__dict__["_batch_locked"] = bool(batch_locked)
        self.frame_shape = tuple(frame_shape)
        c, h, w = self.frame_shape
        self.sizes = torch.tensor([[1, 2], [2, 1]])
        self.shades = torch.tensor([[250, 120, 40], [60, 200, 160]], dtype=torch.uint8)[:, :c]
        if c > 3:
            raise ValueError("at most 3 channels in this test env")
        b = self.batch_size
        image = Bounded(0, 255, (*b, c, h, w), dtype=torch.uint8)
        cells = Unbounded((*b, 2, 2), dtype=torch.int64)
        self.observation_spec = Composite(
            pixels=image, goal_pixels=image.clone(), state=cells, goal_state=cells.clone(), shape=b
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
        rows = torch.arange(h).view(h, 1)
        cols = torch.arange(w).view(1, w)
        frames = torch.zeros(*state.shape[:-2], c, h, w, dtype=torch.uint8)
        for block in range(2):
            top = state[..., block, 0, None, None]
            left = state[..., block, 1, None, None]
            dh, dw = self.sizes[block].tolist()
            inside = (rows >= top) & (rows < top + dh) & (cols >= left) & (cols < left + dw)
            shade = self.shades[block].view(c, 1, 1)
            frames = torch.where(inside.unsqueeze(-3), shade, frames)
        return frames

    def _limits(self):
        _, h, w = self.frame_shape
        return torch.tensor([h, w]) - self.sizes  # highest top-left cell per block

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size if tensordict is None else tensordict.batch_size
        given = tensordict if kwargs.get("set_state", False) else None
        high = self._limits() + 1
        out = {}
        for key in ("state", "goal_state"):
            value = None if given is None else given.get(key, None)
            if value is None:
                value = (torch.rand(*shape, 2, 2, generator=self.rng) * high).long()
            out[key] = value.clone()
        return TensorDict(
            pixels=self.render_state(out["state"]),
            goal_pixels=self.render_state(out["goal_state"]),
            **out,
            batch_size=shape,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        action = DiscreteActions.of(self).index(tensordict["action"]).reshape(-1)
        state = tensordict["state"].reshape(-1, 2, 2).clone()
        block, move = action // 4, MOVES[action % 4]
        rows = torch.arange(state.shape[0])
        moved = state[rows, block] + move
        state[rows, block] = torch.minimum(moved.clamp(min=0), self._limits()[block])
        state = state.reshape(*shape, 2, 2)
        goal = tensordict["goal_state"]
        success = (state == goal).flatten(-2).all(-1, keepdim=True)
        return TensorDict(
            pixels=self.render_state(state),
            goal_pixels=tensordict["goal_pixels"],
            state=state,
            goal_state=goal,
            reward=success.float(),
            done=success,
            terminated=success,
            batch_size=shape,
        )


def make_env(batch_size=(4,), seed=0, device=None, frame_shape=(3, 24, 32)) -> PushBlocksEnv:
    """A 3 x 24 x 32 PushBlocksEnv (the factory an import path names)."""
    return PushBlocksEnv(frame_shape, batch_size=batch_size, seed=seed)


def make_small_env(batch_size=(4,), seed=0, device=None) -> PushBlocksEnv:
    """A gray 1 x 8 x 8 PushBlocksEnv with one-hot actions."""
    return PushBlocksEnv((1, 8, 8), batch_size=batch_size, one_hot=True, seed=seed)


def manhattan(env, state, goal_state):
    """Steps no policy can beat: each block's Manhattan distance to its goal cell."""
    return (state - goal_state).abs().flatten(-2).sum(-1)


#: The profile of the 3 x 24 x 32 env: tiny code and task budgets for the tests.
PUSH_BLOCKS = EnvProfile(
    name="push-blocks",
    make_env=make_env,
    play_trajectory_length=20,
    max_steps=60,
    codes=lambda _: {
        "encoder": {"code_sizes": (6, 6), "channels": 8, "mlp_sizes": (32,)},
        "exclusivity_weight": 1.0,
    },
    lower_bound=manhattan,
    objects=lambda state: state[..., 0] * 100 + state[..., 1],  # each block's cell
    description="two blocks of different shapes on a 3 x 24 x 32 canvas",
)


def block_diagnostics(env, encode, num_samples, seed):
    """The env's own code diagnostics: states drawn by its reset, each one-hot matched to
    the block whose cell best predicts it, its purity and its code map over that block's
    cells."""
    from dorp_rl.metrics import best_assignment, encode_states, majority_codes

    env.set_seed(seed)
    states = torch.cat([env.reset()["state"] for _ in range(-(-num_samples // 4))])
    codes = encode_states(env, encode, states)  # [N, K]
    _, h, w = env.frame_shape
    cells = states[..., 0] * w + states[..., 1]  # [N, 2]
    purity = torch.tensor(
        [[majority_codes(cells[:, b], codes[:, k], h * w)[1] for k in range(codes.shape[1])]
         for b in range(2)]
    )  # fmt: skip
    assignment = best_assignment(purity)
    maps = [None] * codes.shape[1]
    for block, onehot in enumerate(assignment):
        maps[onehot] = majority_codes(cells[:, block], codes[:, onehot], h * w)[0].view(h, w)
    return {
        "num_onehots": codes.shape[1],
        "block_purity": [float(purity[b, k]) for b, k in enumerate(assignment)],
        "code_maps": [None if m is None else m.tolist() for m in maps],
    }


def block_pictures(env, encode, out_dir, result):
    from dorp_rl.viz import plot_code_maps

    return {"code_map": plot_code_maps(result, out_dir / "code_map.png")}


#: The same env with diagnostics of its own, given through its profile.
PUSH_BLOCKS_DIAGNOSED = dataclasses.replace(
    PUSH_BLOCKS,
    name="push-blocks-diagnosed",
    diagnostics=CodeDiagnostics(
        block_diagnostics, block_pictures, lambda env, encode, result: result
    ),
)
