"""Imagined states and their frames, drawn only when a cost needs them
(:class:`ImaginedFrames`, the lazy ``("next", "pixels")`` of the true dynamics).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from dorp_rl.envs.grid_base import (
    GridWorldEnv,
)
from dorp_rl.envs.planning import frame_hash
from dorp_rl.envs.planning.base import _FRAME, _FRAME_BYTES
from dorp_rl.envs.planning.frame_hash import distinct_rows, int64_columns

__all__ = [
    "HeldFrames",
    "ImaginedFrames",
    "RolloutFrames",
]


class ImaginedFrames:
    """Imagined states ``[*L, *state_shape]`` and their frames, drawn only when needed.

    :meth:`GroundTruthModelEnv.imagine` returns one: the states a batch of action
    sequences leads to, i.e. the ``("next", "state")`` of every step, whose
    ``("next", "pixels")`` are ``render_state(states)``; it is the lazy
    ``("next", "pixels")`` of :meth:`GroundTruthModelEnv.imagine_candidates` (a
    :class:`LazyValue`). Costs read it as they read :class:`HeldFrames` (through
    :meth:`dorp_rl.planners.CandidateRollout.frames`), asking for what they need instead
    of the frames themselves:

    - :meth:`pixels` (also :meth:`materialize`): all frames, uint8 ``[*L, 3, 16, 16]``
      (drawn once, then kept);
    - :meth:`distinct`: exactly what :func:`distinct_rows` gives on the frames (with
      optional extra int64 columns), drawing only the distinct frames;
    - :meth:`squared_distances`: the exact squared L2 distance of each frame to a goal
      image, from the frame's parts, drawing no frame.

    The last two need an env whose frames are sums of non-overlapping parts
    (:meth:`~dorp_rl.envs.GridWorldEnv.frame_parts`) and valid start states (blocks that
    overlap would not add up); otherwise they fall back to drawing every frame, with the
    same results.

    Args:
        env: the environment whose renderer draws the states.
        states: int64 ``[*L, *state_shape]``.
        parts_valid: whether the states' frames are the sums of their parts (valid
            states of an env with :meth:`~dorp_rl.envs.GridWorldEnv.frame_parts`).
        tables: a dict the derived part tables are cached in (shared between calls).

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(3,), seed=0)
        >>> td = env.reset()
        >>> actions = torch.randint(0, 8, (3, 5, 4))  # 5 sequences of 4 actions per row
        >>> frames = GroundTruthModelEnv(env).imagine(td["state"].unsqueeze(1), actions)
        >>> frames.states.shape, frames.pixels().shape
        (torch.Size([3, 5, 4, 2, 2]), torch.Size([3, 5, 4, 3, 16, 16]))
        >>> goal = td["goal_pixels"].reshape(3, -1)
        >>> owner = torch.arange(3).view(3, 1, 1).expand(3, 5, 4).reshape(-1)
        >>> d2 = frames.squared_distances(goal, owner)
        >>> plain = (frames.pixels().reshape(-1, 768).long() - goal[owner].long()).square().sum(-1)
        >>> bool((d2 == plain).all())
        True
    """

    def __init__(
        self,
        env: GridWorldEnv,
        states: torch.Tensor,
        *,
        parts_valid: bool = True,
        tables: dict | None = None,
    ) -> None:
        self.env = env
        self.states = states
        self.shape = states.shape[: states.dim() - len(env.state_shape)]
        self.frame_shape = torch.Size(_FRAME)
        self._tables = {} if tables is None else tables
        self._pixels: torch.Tensor | None = None
        self._parts: torch.Tensor | None = None
        table = env.frame_part_table() if parts_valid else None
        self._has_parts = table is not None and env.frame_parts(states[:0]) is not None

    @property
    def numel(self) -> int:
        return int(self.shape.numel())

    def pixels(self) -> torch.Tensor:
        """uint8 ``[*L, 3, 16, 16]``: every frame (``env.render_state(states)``)."""
        if self._pixels is None:
            self._pixels = self.env.render_state(self.states)
        return self._pixels

    def materialize(self) -> torch.Tensor:
        """:meth:`pixels`: the frames stepping the env would have written (:class:`LazyValue`)."""
        return self.pixels()

    def _flat_states(self) -> torch.Tensor:
        return self.states.reshape(self.numel, *self.env.state_shape)

    def _flat_parts(self) -> torch.Tensor:
        if self._parts is None:
            self._parts = self.env.frame_parts(self._flat_states())
        return self._parts

    def _table(self, name: str) -> torch.Tensor:
        """Derived part tables, computed once per env and device."""
        key = (name, self.states.device)
        if key not in self._tables:
            parts = self.env.frame_part_table().to(self.states.device).reshape(-1, _FRAME_BYTES)
            if name == "float64":
                value = parts.to(torch.float64)
            elif name == "norms":
                value = parts.to(torch.int64).square().sum(-1)
            else:  # part hashes for rows of `name` bytes
                weights = frame_hash.hash_weights(self.states.device, name)[: parts.shape[1]]
                value = (parts.to(torch.int64) * weights).sum(-1)
            self._tables[key] = value
        return self._tables[key]

    def distinct(
        self, extra: torch.Tensor | None = None, *, draw: bool = True
    ) -> tuple[
        torch.Tensor | Callable[[torch.Tensor | None], torch.Tensor],
        torch.Tensor | None,
        torch.Tensor | None,
        torch.Tensor | None,
    ]:
        """:func:`distinct_rows` of the frames (joined with ``extra`` columns), drawing distinct ones.

        Args:
            extra: int64 ``[n, e]`` joined to each flat frame (``n = prod(L)``), as its
                bytes; ``None`` for the frames alone.
            draw: ``False`` returns, instead of the distinct frames, a function drawing
                those of given indices (``None``: all), when the rows were found without
                drawing them (a cache keyed by ``keys`` may need only a few).

        Returns:
            ``(frames, extra, inverse, keys)``: the rows ``distinct_rows`` returns on
            ``cat(frames.reshape(n, -1), extra.view(uint8))``, split into uint8 frames
            ``[m, 3, 16, 16]`` (or the function drawing them) and int64 extras ``[m, e]``
            (``None`` without ``extra``); its ``inverse`` (``None``: no deduplication, all
            ``n`` rows returned); and :func:`row_hashes` of the returned rows (``None``
            when not known).
        """
        n = self.numel
        if not self._has_parts or n <= 1:
            return self._distinct_drawn(extra)
        parts = self._flat_parts()
        num_bytes = _FRAME_BYTES + (0 if extra is None else 8 * extra.shape[1])
        key = self._table(num_bytes)[parts].sum(-1)  # the hash is linear in the bytes
        if extra is not None:
            extra_bytes = extra.contiguous().view(torch.uint8).to(torch.int64)
            weights = frame_hash.hash_weights(key.device, num_bytes)[_FRAME_BYTES:]
            key = key + (extra_bytes * weights).sum(-1)
        unique, inverse = torch.unique(key, return_inverse=True)
        first = torch.full((unique.shape[0],), n, dtype=torch.long, device=key.device)
        first.scatter_reduce_(0, inverse, torch.arange(n, device=key.device), reduce="amin")
        # distinct_rows checks that every row equals its group's first row: equal parts
        # (and extras) mean equal bytes; rows that differ there are compared as frames.
        owner = first[inverse]
        differ = (parts[owner] != parts).any(-1)
        if extra is not None:
            differ |= (extra[owner] != extra).any(-1)
        if bool(differ.any()):
            rows = differ.nonzero().squeeze(-1)
            states = self._flat_states()
            same = torch.equal(
                self.env.render_state(states[rows]), self.env.render_state(states[owner[rows]])
            )
            if extra is not None:
                same = same and torch.equal(extra[rows], extra[owner[rows]])
            if not same:  # a hash collision: distinct_rows gives up deduplication
                return self._distinct_drawn(extra)
        states = self._flat_states()[first]

        def draw_frames(index: torch.Tensor | None = None) -> torch.Tensor:
            return self.env.render_state(states if index is None else states[index])

        frames = draw_frames() if draw else draw_frames
        return frames, None if extra is None else extra[first], inverse, unique

    def _distinct_drawn(self, extra: torch.Tensor | None):
        """:meth:`distinct` by drawing every frame and calling :func:`distinct_rows`."""
        return HeldFrames(self.pixels()).distinct(extra)

    def squared_distances(self, goals: torch.Tensor, owner: torch.Tensor) -> torch.Tensor | None:
        """Exact squared L2 distances int64 ``[n]`` of the frames to their goal images.

        Frame ``i`` (flat index over ``L``) is compared with ``goals[owner[i]]``, in
        integer arithmetic on the 0..255 values. Computed from the frames' parts:
        ``|f - g|^2 = |g|^2 + sum_p (|part_p|^2 - 2 <part_p, g>)`` (parts do not overlap).

        Args:
            goals: uint8 ``[G, 768]`` goal frames (flat).
            owner: int64 ``[n]``, the goal of each frame.

        Returns:
            int64 ``[n]``, or ``None`` when the frames are not sums of parts (draw them).
        """
        if not self._has_parts or goals.dtype != torch.uint8:
            return None
        table = self._table("float64")  # [T, 768]
        g = goals.reshape(goals.shape[0], -1).to(table.device, torch.float64)
        # Integers below 2**53 throughout (768 * 255**2 at most): the products are exact.
        dots = (table @ g.T).to(torch.int64)  # [T, G]
        per_part = (self._table("norms").unsqueeze(-1) - 2 * dots).T.contiguous()  # [G, T]
        goal_norms = g.square().sum(-1).to(torch.int64)  # [G]
        parts = self._flat_parts()
        index = owner.unsqueeze(-1) * per_part.shape[1] + parts
        return goal_norms[owner] + per_part.reshape(-1)[index].sum(-1)


class HeldFrames:
    """Frames a rollout holds as a tensor ``[*L, C, H, W]`` (a stepped env's), read through
    the interface of :class:`ImaginedFrames`, so that a cost has one implementation for
    both: :meth:`pixels`, :meth:`distinct` (:func:`distinct_rows` on uint8 frames; other
    dtypes, and a single frame, are not deduplicated) and :meth:`squared_distances`
    (``None``: the cost computes them from the frames).

    Examples:
        >>> import torch
        >>> from dorp_rl.envs.planning import HeldFrames
        >>> pixels = torch.zeros(2, 3, 3, 4, 4, dtype=torch.uint8)
        >>> pixels[1] = 7
        >>> frames, _, inverse, _ = HeldFrames(pixels).distinct()
        >>> frames.shape[0], inverse.tolist()
        (2, [0, 0, 0, 1, 1, 1])
    """

    def __init__(self, pixels: torch.Tensor) -> None:
        if pixels.dim() < 3:
            raise ValueError(f"frames must be [*L, C, H, W], got shape {list(pixels.shape)}.")
        self._pixels = pixels
        self.shape = pixels.shape[:-3]
        self.frame_shape = pixels.shape[-3:]

    @property
    def numel(self) -> int:
        return int(self.shape.numel())

    def pixels(self) -> torch.Tensor:
        """The frames ``[*L, C, H, W]``."""
        return self._pixels

    def materialize(self) -> torch.Tensor:
        return self._pixels

    def distinct(
        self, extra: torch.Tensor | None = None, *, draw: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, None]:
        """As :meth:`ImaginedFrames.distinct` (``draw`` is moot: the frames are held)."""
        n = self.numel
        flat = self._pixels.reshape(n, *self.frame_shape)
        if flat.dtype != torch.uint8 or n <= 1:
            return flat, extra, None, None
        if extra is None:
            rows, inverse = distinct_rows(flat)
            return rows, None, inverse, None
        width = flat[0].numel()
        rows, inverse = distinct_rows(
            torch.cat([flat.reshape(n, -1), extra.contiguous().view(torch.uint8)], -1)
        )
        frames = rows[:, :width].reshape(-1, *self.frame_shape)
        return frames, int64_columns(rows[:, width:]), inverse, None

    def squared_distances(self, goals: torch.Tensor, owner: torch.Tensor) -> None:
        """``None``: held frames have no parts to add up (the cost compares the frames)."""
        return None


#: The frames of a rollout as a cost reads them: held, or imagined and drawn on demand.
RolloutFrames = HeldFrames | ImaginedFrames
