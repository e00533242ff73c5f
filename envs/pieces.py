"""PiecesEnv: pieces of any shapes and colours sliding on a grid drawn at any scale.

A configurable stateless env for checking the pipeline on envs it was not tuned for
(objects of one colour that differ only in shape, large frames, many pieces). Its step
reads ``step_count`` from the tensordict besides ``state`` and counts it on, as torchrl's
stateless envs read their observation entries.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["PiecesEnv", "cells_of", "manhattan"]

MOVES = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]])  # up, down, left, right


def cells_of(rows: list[str]) -> torch.Tensor:
    """The ``[n, 2]`` cells marked ``#`` in a drawing of a shape."""
    return torch.tensor(
        [[r, c] for r, row in enumerate(rows) for c, ch in enumerate(row) if ch == "#"]
    )


class PiecesEnv(EnvBase):
    """Pieces on a ``grid`` of cells drawn ``scale`` pixels a cell; ``state`` int64
    ``[*B, K, 2]`` (each piece's top-left cell), ``step_count`` int64 ``[*B, 1]``.

    Action ``4 * piece + direction`` (0 up, 1 down, 2 left, 3 right) moves one piece one
    cell unless it would leave the grid or overlap another. A task is solved when
    ``state`` equals ``goal_state``. With ``batch_size=()`` and ``batch_locked=False`` it
    steps any leading shape (its own true dynamics).

    Examples:
        >>> from dorp_rl.envs.pieces import PiecesEnv, cells_of
        >>> shapes = [cells_of(["##"]), cells_of(["#", "#"])]
        >>> env = PiecesEnv(shapes, [(255, 255, 255)] * 2, grid=(6, 8), scale=2, batch_size=(3,))
        >>> td = env.rollout(4, break_when_any_done=False)
        >>> td["next", "pixels"].shape, td["next", "step_count"][0, :, 0].tolist()
        (torch.Size([3, 4, 3, 12, 16]), [1, 2, 3, 4])
    """

    _supports_set_state = True

    def __init__(
        self,
        shapes: list[torch.Tensor],
        colours: list[tuple[int, int, int]],
        grid: tuple[int, int],
        scale: int = 1,
        batch_size=(8,),
        seed: int = 0,
        device=None,
        batch_locked: bool = True,
        channels: int = 3,
    ):
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        if channels not in (1, 3):
            raise ValueError(
                f"channels must be 1 (grey, a colour's first entry) or 3, got {channels}."
            )
        self.__dict__["_batch_locked"] = bool(batch_locked)
        self.shapes, self.grid, self.scale = shapes, tuple(grid), int(scale)
        self.colours = torch.tensor(colours, dtype=torch.uint8)[:, :channels]
        self.span = torch.stack([s.max(0).values + 1 for s in shapes])  # [K, 2]
        k, (h, w) = len(shapes), self.grid
        b = self.batch_size
        image = Bounded(0, 255, (*b, channels, h * self.scale, w * self.scale), dtype=torch.uint8)
        cells = Unbounded((*b, k, 2), dtype=torch.int64)
        self.observation_spec = Composite(
            pixels=image,
            goal_pixels=image.clone(),
            state=cells,
            goal_state=cells.clone(),
            step_count=Unbounded((*b, 1), dtype=torch.int64),
            shape=b,
        )
        self.action_spec = Categorical(4 * k, shape=(*b, 1))
        self.reward_spec = Unbounded((*b, 1))
        self.rng = torch.Generator()
        self.set_seed(seed)

    def _set_seed(self, seed):
        self.rng.manual_seed(0 if seed is None else int(seed))

    def occupied(self, state: torch.Tensor) -> torch.Tensor:
        """Bool ``[*B, K, H, W]`` (grid cells): the cells of each piece."""
        h, w = self.grid
        lead = state.shape[:-2]
        masks = []
        for k, cells in enumerate(self.shapes):
            rows = (state[..., k, 0, None] + cells[:, 0]).clamp(0, h - 1)
            cols = (state[..., k, 1, None] + cells[:, 1]).clamp(0, w - 1)
            flat = torch.zeros(*lead, h * w, dtype=torch.bool)
            flat.scatter_(-1, rows * w + cols, True)
            masks.append(flat.reshape(*lead, h, w))
        return torch.stack(masks, -3)

    def render(self, state: torch.Tensor) -> torch.Tensor:
        masks = self.occupied(state)
        h, w = self.grid
        c = self.colours.shape[1]
        frames = torch.zeros(*state.shape[:-2], c, h, w, dtype=torch.uint8)
        for k in range(len(self.shapes)):
            frames = torch.where(masks[..., k, None, :, :], self.colours[k].view(c, 1, 1), frames)
        if self.scale > 1:
            frames = frames.repeat_interleave(self.scale, -2).repeat_interleave(self.scale, -1)
        return frames

    def _valid(self, state: torch.Tensor) -> torch.Tensor:
        top = torch.tensor(self.grid) - self.span
        inside = ((state >= 0) & (state <= top)).flatten(-2).all(-1)
        overlap = (self.occupied(state).sum(-3) > 1).flatten(-2).any(-1)
        return inside & ~overlap

    def _draw(self, shape: torch.Size) -> torch.Tensor:
        k = len(self.shapes)
        state = torch.zeros(*shape, k, 2, dtype=torch.int64)
        todo = torch.ones(shape, dtype=torch.bool)
        high = (torch.tensor(self.grid) - self.span + 1).float()
        while bool(todo.any()):
            draw = (torch.rand(*shape, k, 2, generator=self.rng) * high).long()
            state = torch.where(todo[..., None, None], draw, state)
            todo = ~self._valid(state)
        return state

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size if tensordict is None else tensordict.batch_size
        given = tensordict if kwargs.get("set_state", False) else None
        out = {}
        for key in ("state", "goal_state"):
            value = None if given is None else given.get(key, None)
            out[key] = self._draw(shape) if value is None else value.clone()
        return TensorDict(
            pixels=self.render(out["state"]),
            goal_pixels=self.render(out["goal_state"]),
            step_count=torch.zeros(*shape, 1, dtype=torch.int64),
            **out,
            batch_size=shape,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        k = len(self.shapes)
        action = tensordict["action"].reshape(-1)
        state = tensordict["state"].reshape(-1, k, 2)
        moved = state.clone()
        rows = torch.arange(state.shape[0])
        moved[rows, action // 4] += MOVES[action % 4]
        state = torch.where(self._valid(moved)[:, None, None], moved, state).reshape(*shape, k, 2)
        goal = tensordict["goal_state"]
        solved = (state == goal).flatten(-2).all(-1, keepdim=True)
        return TensorDict(
            pixels=self.render(state),
            goal_pixels=tensordict["goal_pixels"],
            state=state,
            goal_state=goal,
            step_count=tensordict["step_count"] + 1,
            reward=solved.float(),
            done=solved,
            terminated=solved,
            batch_size=shape,
        )


def manhattan(env, state: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """Sum over pieces of the Manhattan distance to the goal cell: no policy needs fewer."""
    return (state - goal).abs().flatten(-2).sum(-1)
