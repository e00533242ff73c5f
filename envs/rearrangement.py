"""k-object rearrangement: coloured blocks on a 16x16 grid, moved one cell at a time."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from dorp_rl.envs.grid_base import (
    DIRECTIONS,
    GRID_SIZE,
    GridWorldEnv,
    colour_codes,
    draw_grid_tasks,
    paint_layers,
)
from dorp_rl.envs.profile import EnvProfile, register_env_profile
from dorp_rl.envs.rearrangement_diagnostics import REARRANGEMENT_DIAGNOSTICS
from dorp_rl.validation import check_int

#: Block colours in object order (the authors' first five, then two more).
OBJECT_COLOURS = torch.tensor(
    [
        [255, 255, 0],  # yellow
        [0, 255, 255],  # cyan
        [160, 32, 240],  # purple
        [255, 0, 0],  # red
        [0, 255, 0],  # green
        [0, 96, 255],  # blue
        [255, 255, 255],  # white
        [255, 140, 0],  # orange
    ],
    dtype=torch.uint8,
)

#: Step limits of the paper's tasks per number of objects.
DEFAULT_MAX_STEPS = {1: 200, 2: 400, 3: 600, 4: 1000, 5: 1400, 6: 1800}

_MAX_REJECTION_ROUNDS = 10_000


class ObjectRearrangementEnv(GridWorldEnv):
    """The paper's k-object rearrangement as a batched, stateless TorchRL env.

    ``state`` is int64 ``[*B, k, 2]``: the (row, column) of each block's top-left cell.
    Action ``a`` (of ``4 k``) moves block ``a // 4`` one cell in direction ``a % 4``
    (0 up, 1 down, 2 left, 3 right). A move that would leave the grid or overlap another
    block does nothing. Random configurations are uniform over valid placements.

    Args:
        num_objects: number of blocks ``k`` (at least 1, at most the number of colours).
        block_shapes: ``(rows, cols)`` of every block, or one pair per block.
            Defaults to the paper's 2 x 4.
        colours: uint8 ``[k, 3]`` RGB colours; defaults to :data:`OBJECT_COLOURS`.
        max_steps: step limit; defaults to the paper's (200, 400, 600, 1000, 1400, 1800
            for 1..6 objects).
        **kwargs: forwarded to :class:`~dorp_rl.envs.GridWorldEnv` (``batch_size``,
            ``device``, ``seed``, ``batch_locked``, ``terminate_on_success``).

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(4,), seed=0)
        >>> td = env.rollout(3)
        >>> td["pixels"].shape, td["state"].shape
        (torch.Size([4, 3, 3, 16, 16]), torch.Size([4, 3, 2, 2]))
    """

    def __init__(
        self,
        num_objects: int = 1,
        *,
        block_shapes: Sequence[int] | Sequence[Sequence[int]] = (2, 4),
        colours: torch.Tensor | None = None,
        max_steps: int | None = None,
        **kwargs,
    ) -> None:
        num_objects = check_int("num_objects", num_objects, low=1)
        self.num_objects = num_objects
        self.block_shapes = self._parse_block_shapes(block_shapes, num_objects)
        if colours is None:
            if num_objects > len(OBJECT_COLOURS):
                raise ValueError(
                    f"num_objects={num_objects} needs distinct colours: the default palette "
                    f"has {len(OBJECT_COLOURS)}; pass colours=[k, 3] for more."
                )
            colours = OBJECT_COLOURS[:num_objects]
        colours = torch.as_tensor(colours)
        out_of_range = colours.numel() and (int(colours.min()) < 0 or int(colours.max()) > 255)
        if colours.is_floating_point() or colours.dtype == torch.bool or out_of_range:
            raise ValueError(
                f"colours must hold integer RGB values in [0, 255], got {colours.tolist()}."
            )
        colours = colours.to(torch.uint8)
        if colours.shape != (num_objects, 3):
            raise ValueError(
                f"colours must have shape [{num_objects}, 3], got {list(colours.shape)}."
            )
        if len({tuple(c) for c in colours.tolist()}) != num_objects or (colours == 0).all(-1).any():
            raise ValueError("colours must be distinct and not black (the background).")
        area = int(self.block_shapes.prod(-1).sum())
        if area > GRID_SIZE * GRID_SIZE:
            raise ValueError(
                f"num_objects={num_objects} blocks of shapes {self.block_shapes.tolist()} cover "
                f"{area} cells; at most {GRID_SIZE * GRID_SIZE} fit the {GRID_SIZE}x{GRID_SIZE} grid."
            )
        if max_steps is None:
            max_steps = DEFAULT_MAX_STEPS.get(num_objects, 400 * num_objects - 200)
        self._colours_cpu = colours
        self._check_placeable()
        super().__init__(max_steps=max_steps, **kwargs)
        self._object_ids = torch.arange(num_objects, device=self.device)
        self.block_shapes = self.block_shapes.to(self.device)
        self.colours = colours.to(self.device)
        self._frame_table = self._build_frame_table()
        # Each frame's 768 bytes seen as 96 int64 words: see render_state.
        self._frame_words = self._frame_table.reshape(-1, 3 * GRID_SIZE * GRID_SIZE).view(
            torch.int64
        )

    def _check_placeable(self, attempts: int = 4096) -> None:
        """Raises ``ValueError`` if no valid placement turns up in ``attempts`` random draws."""
        gen = torch.Generator().manual_seed(0)
        span = (GRID_SIZE - self.block_shapes + 1).to(torch.float64)
        draws = (
            torch.rand((attempts, self.num_objects, 2), generator=gen, dtype=torch.float64) * span
        )
        if self._overlaps(draws.floor().to(torch.int64)).all():
            raise ValueError(
                f"num_objects={self.num_objects} blocks of shapes {self.block_shapes.tolist()} "
                f"cannot be placed without overlap on the {GRID_SIZE}x{GRID_SIZE} grid "
                f"(no valid placement in {attempts} random draws); use fewer or smaller blocks."
            )

    @staticmethod
    def _parse_block_shapes(block_shapes, num_objects: int) -> torch.Tensor:
        shapes = torch.as_tensor(block_shapes)
        if shapes.is_floating_point() and not bool((shapes == shapes.round()).all()):
            raise ValueError(f"block_shapes must hold integer sides, got {shapes.tolist()}.")
        if shapes.dtype == torch.bool or shapes.is_complex():
            raise ValueError(f"block_shapes must hold integer sides, got {shapes.tolist()}.")
        shapes = shapes.to(torch.int64)
        if shapes.shape == (2,):
            shapes = shapes.expand(num_objects, 2).clone()
        if shapes.shape != (num_objects, 2):
            raise ValueError(
                f"block_shapes must be one (rows, cols) pair or {num_objects} of them, "
                f"got shape {list(shapes.shape)}."
            )
        if (shapes < 1).any() or (shapes > GRID_SIZE).any():
            raise ValueError(f"block sides must be in [1, {GRID_SIZE}], got {shapes.tolist()}.")
        return shapes

    def oracle_layout(self) -> tuple[torch.Tensor, bool]:
        """What :class:`~dorp_rl.envs.OracleCodeEncoder` codes: each block by the
        position of its colour (int64 ``[K, 3]``), no key bit."""
        return self.colours.to(torch.int64), False

    def config(self) -> dict:
        return {
            **super().config(),
            "num_objects": self.num_objects,
            "block_shapes": self.block_shapes.tolist(),
            "colours": self.colours.tolist(),
        }

    @property
    def num_actions(self) -> int:
        return 4 * self.num_objects

    @property
    def state_shape(self) -> torch.Size:
        return torch.Size([self.num_objects, 2])

    def _state_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        high = GRID_SIZE - self.block_shapes.cpu()
        return torch.zeros_like(high), high

    # ------------------------------------------------------------------ #
    def _overlaps(self, state: torch.Tensor) -> torch.Tensor:
        """bool ``[*B]``: whether any two blocks share a cell."""
        top, left = state[..., 0], state[..., 1]  # [*B, k]
        bottom = top + self.block_shapes[:, 0]
        right = left + self.block_shapes[:, 1]
        rows = (top.unsqueeze(-1) < bottom.unsqueeze(-2)) & (
            top.unsqueeze(-2) < bottom.unsqueeze(-1)
        )
        cols = (left.unsqueeze(-1) < right.unsqueeze(-2)) & (
            left.unsqueeze(-2) < right.unsqueeze(-1)
        )
        eye = torch.eye(self.num_objects, dtype=torch.bool, device=state.device)
        return (rows & cols & ~eye).flatten(-2).any(-1)

    def _off_grid(self, state: torch.Tensor) -> torch.Tensor:
        outside = (state < 0) | (state + self.block_shapes > GRID_SIZE)
        return outside.flatten(-2).any(-1)

    def invalid_states(self, state: torch.Tensor) -> torch.Tensor:
        return self._off_grid(state) | self._overlaps(state)

    def _describe_invalid(self, state: torch.Tensor, bad: torch.Tensor) -> str:
        return "blocks must lie inside the 16x16 grid and must not overlap"

    def sample_states(self, shape: torch.Size) -> torch.Tensor:
        """Uniform over valid placements, by rejection of overlapping draws."""
        n = int(torch.Size(shape).numel())
        out = torch.empty((n, self.num_objects, 2), dtype=torch.int64, device=self.device)
        span = (GRID_SIZE - self.block_shapes + 1).to(torch.float64)  # [k, 2]
        todo = torch.arange(n, device=self.device)
        for _ in range(_MAX_REJECTION_ROUNDS):
            if todo.numel() == 0:
                return out.view(*shape, self.num_objects, 2)
            u = torch.rand(
                (todo.numel(), self.num_objects, 2), generator=self.rng, device=self.device
            )
            cand = (u.to(torch.float64) * span).floor().to(torch.int64)
            ok = ~self._overlaps(cand)
            out[todo[ok]] = cand[ok]
            todo = todo[~ok]
        raise ValueError(
            f"could not place {self.num_objects} blocks of shapes {self.block_shapes.tolist()} "
            f"without overlap after {_MAX_REJECTION_ROUNDS} rounds of rejection sampling."
        )

    #: whether :meth:`transitions` may roll this class's moves out its own way (see
    #: ``__init_subclass__``)
    _fast_transitions = True

    def __init_subclass__(cls, **kwargs) -> None:
        # transitions below rolls out this class's moves: not those of a subclass that
        # redefines transition (nor of its subclasses), which get the generic loop.
        super().__init_subclass__(**kwargs)
        if "transition" in vars(cls):
            cls._fast_transitions = False

    def transition(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        obj = action // 4
        delta = DIRECTIONS.to(state.device)[action % 4]  # [*B, 2]
        corner = torch.gather(state, -2, obj[..., None, None].expand(*obj.shape, 1, 2)).squeeze(-2)
        target = corner + delta  # new top-left of the moved block, [*B, 2]
        size = self.block_shapes[obj]  # [*B, 2]
        inside = ((target >= 0) & (target + size <= GRID_SIZE)).all(-1)
        # Only the moved block can create an overlap: test it against every other block.
        others_low, others_high = state, state + self.block_shapes  # [*B, k, 2]
        hits = (
            (target.unsqueeze(-2) < others_high) & (others_low < (target + size).unsqueeze(-2))
        ).all(-1)  # [*B, k]
        hits &= self._object_ids != obj.unsqueeze(-1)
        ok = inside & ~hits.any(-1)
        new_corner = torch.where(ok.unsqueeze(-1), target, corner)
        index = obj[..., None, None].expand(*obj.shape, 1, 2)
        return state.scatter(-2, index, new_corner.unsqueeze(-2))

    def transitions(self, state: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """:meth:`transition` ``H`` times (``[*L, H, k, 2]``), about twice as fast.

        The moves are decoded for all steps at once, and rows and columns are kept
        apart in int16 (coordinates are below 16), so each step is a few small kernels.
        A subclass that defines its own :meth:`transition` gets the step-by-step rollout.
        """
        if not self._fast_transitions:
            return super().transitions(state, actions)
        lead, horizon, k = actions.shape[:-1], actions.shape[-1], self.num_objects
        small = torch.int16
        obj = actions // 4  # [*L, H]
        direction = DIRECTIONS.to(state.device, small)[actions % 4]  # [*L, H, 2]
        shapes = self.block_shapes.to(small)
        size = shapes[obj]  # [*L, H, 2]
        heights, widths = shapes[:, 0].contiguous(), shapes[:, 1].contiguous()
        mine = obj.unsqueeze(-1) == self._object_ids  # [*L, H, k]
        rows = state[..., 0].to(small).expand(*lead, k).contiguous()
        cols = state[..., 1].to(small).expand(*lead, k).contiguous()
        all_rows, all_cols = [], []
        for t in range(horizon):
            moved = obj[..., t : t + 1]
            top = rows.gather(-1, moved) + direction[..., t, :1]  # [*L, 1]
            left = cols.gather(-1, moved) + direction[..., t, 1:]
            height, width = size[..., t, :1], size[..., t, 1:]
            inside = (top >= 0) & (top + height <= GRID_SIZE) & (left >= 0)
            inside &= left + width <= GRID_SIZE
            hits = (top < rows + heights) & (rows < top + height)
            hits &= (left < cols + widths) & (cols < left + width)
            hits &= ~mine[..., t, :]
            move = mine[..., t, :] & (inside & ~hits.any(-1, keepdim=True))
            rows = torch.where(move, top, rows)
            cols = torch.where(move, left, cols)
            all_rows.append(rows)
            all_cols.append(cols)
        step = len(lead)
        out = torch.stack([torch.stack(all_rows, step), torch.stack(all_cols, step)], -1)
        return out.to(torch.int64)

    def _build_frame_table(self) -> torch.Tensor:
        """uint8 ``[k * 256, 3, 16, 16]``: object ``o`` alone with its top-left at cell ``p``.

        Rendering a state is then one gather and a sum over objects (blocks never overlap),
        instead of rasterising rectangles at every step.
        """
        rows, cols = self._coords()
        cell = torch.arange(GRID_SIZE * GRID_SIZE, device=self.device)
        top = (cell // GRID_SIZE).view(1, -1, 1, 1)
        left = (cell % GRID_SIZE).view(1, -1, 1, 1)
        height = self.block_shapes[:, 0].view(-1, 1, 1, 1)
        width = self.block_shapes[:, 1].view(-1, 1, 1, 1)
        masks = (rows >= top) & (rows < top + height) & (cols >= left) & (cols < left + width)
        frames = torch.stack(
            [
                paint_layers(masks[o].unsqueeze(-3), self.colours[o : o + 1])
                for o in range(self.num_objects)
            ]
        )  # [k, 256, 3, H, W]
        return frames.reshape(self.num_objects * GRID_SIZE * GRID_SIZE, 3, GRID_SIZE, GRID_SIZE)

    def frame_parts(self, state: torch.Tensor) -> torch.Tensor:
        """int64 ``[*B, k]``: block ``o`` alone at its cell, a row of :meth:`frame_part_table`."""
        return self._part_index(state)

    def _part_index(self, state: torch.Tensor) -> torch.Tensor:
        cell = state[..., 0].clamp(0, GRID_SIZE - 1) * GRID_SIZE + state[..., 1].clamp(
            0, GRID_SIZE - 1
        )
        return cell + self._object_ids * (GRID_SIZE * GRID_SIZE)

    def frame_part_table(self) -> torch.Tensor:
        """uint8 ``[k * 256, 3, 16, 16]``: every block alone at every cell."""
        return self._frame_table

    def render_state(self, state: torch.Tensor) -> torch.Tensor:
        """Draws valid states ``[*B, k, 2]`` as uint8 ``[*B, 3, 16, 16]`` (black background).

        Frames are gathered and summed as int64 words (8 pixels' bytes each): blocks never
        overlap, so every byte has at most one non-zero term and no carry crosses bytes.
        """
        index = self._part_index(state).reshape(-1)
        words = self._frame_words.index_select(0, index)
        words = words.view(-1, self.num_objects, words.shape[-1])
        if self.num_objects > 1:
            words = words.sum(1)
        frames = words.reshape(-1).view(torch.uint8)
        return frames.view(*state.shape[:-2], 3, GRID_SIZE, GRID_SIZE)

    def states_from_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """int64 ``[*B, k, 2]``: the first row and column holding each block's colour.

        A block whose colour is missing reads as (0, 0); :meth:`invalid_frames` then finds
        that the frame is no render of the state read.
        """
        codes = colour_codes(frames.to(self.device))  # [*B, 16, 16]
        mine = colour_codes(self.colours.t().reshape(3, -1, 1)).reshape(-1, 1, 1)  # [k, 1, 1]
        masks = codes.unsqueeze(-3) == mine  # [*B, k, 16, 16]
        rows = masks.any(-1).to(torch.int64).argmax(-1)
        cols = masks.any(-2).to(torch.int64).argmax(-1)
        return torch.stack([rows, cols], -1)

    def frame_colours(self) -> torch.Tensor:
        """uint8 ``[k + 1, 3]``: black, then the blocks' colours."""
        return torch.cat([self.colours.new_zeros(1, 3), self.colours])

    def describe_world(self) -> str:
        return f"{type(self).__name__} with {self.num_objects} object(s)"

    def _lower_bound_steps(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        """Sum over blocks of the Manhattan distance to the goal corner."""
        return (state - goal_state).abs().flatten(-2).sum(-1)


def _rearrangement_codes(num_objects: int) -> dict:
    """The code preset of k blocks: one one-hot per block (16 codes for one block, 32 for
    more), with the step and play budgets of the measured runs."""
    return {
        "encoder": {"code_sizes": (32 if num_objects > 1 else 16,)},
        "num_steps": {1: 1500, 2: 1500, 3: 2000, 6: 4000}.get(num_objects, 3000),
        "num_frames": {1: 60_000, 2: 100_000, 3: 150_000, 6: 250_000}.get(num_objects, 200_000),
    }


def _rearrangement_latent_model(num_objects: int) -> dict:
    """The grid envs' latent model with more play data and steps (docs/NOTES.md has the
    measurements): a latent map's codes were right on more open-loop steps than an MLP
    latent's in less training time, and the MLP decoder's as often as transposed
    convolutions'. Up to 2 blocks, a 4 x 4 map stepped by convolutions twice as wide as
    the key rooms'. From 3 blocks on, an 8 x 8 map (stride 2), right on more steps where
    a block's one-pixel move is a quarter of a 4 x 4 cell:

    - at 3 and 4 blocks 16 channels deep, stepped by three narrow convolutions that take
      the action as a vector (cheap enough to plan through), trained at a higher
      learning rate (far faster) for 5000 steps that decode 4 random steps of each
      window (as accurate as decoding all, in a fifth less time);
    - from 5 blocks on, where the true dynamics cost more too, 32 channels stepped by
      convolutions twice as wide (their one-step errors compounded less over 14 steps),
      with the decoded frames' error at the values a step changed weighted on its own
      (a block's sideways move changes a dozen of 768 values: without it the model left
      some blocks where they were), trained twice as long on twice the play data,
      decoding 4 random steps of each window.
    """
    fields: dict = {}
    if num_objects >= 5:
        model = {"latent_stride": 2, "dynamics_channels": 64}
        fields = {
            "change_weight": 10.0,
            "pixel_steps": 4,
            "num_steps": 12_000,
            "num_frames": 400_000,
        }
    elif num_objects >= 3:
        narrow = {"latent_channels": 16, "dynamics_channels": 16, "dynamics_layers": 3}
        model = {"latent_stride": 2, **narrow, "action_planes": False}
        fields = {"lr": 3e-3, "pixel_steps": 4, "num_steps": 5000}
    else:
        model = {"dynamics_channels": 64}
    return {
        "num_frames": 200_000,
        "num_steps": 6000,
        **fields,
        "model": model,
    }


def _rearrangement_dorp(num_objects: int) -> dict:
    """DORP's settings (docs/NOTES.md has the measurements): failed hops are removed at
    once (blocks stand in the way) and waypoint plans are ranked by the goal image too.
    From 5 blocks on, a latent model's goal-image phase judges decoded frames, not
    latents: imagined latents of five blocks drift apart from the real frames', and
    the phase stalled where decoded frames reached the goal."""
    fields = {"reenter": False, "replan_on_miss": False, "waypoint_goal_weight": 0.003}
    if num_objects >= 5:
        fields["goal_latent_weight"] = 0.0
    return fields


#: k-object rearrangement as the pipeline sees it (``--env rearrangement``).
REARRANGEMENT = register_env_profile(
    EnvProfile(
        name="rearrangement",
        make_env=ObjectRearrangementEnv,
        counts_objects=True,
        env_type=ObjectRearrangementEnv,
        max_steps=lambda k: DEFAULT_MAX_STEPS.get(k, 400 * k - 200),
        code_layout=lambda size, k: (size,) * k,
        codes=_rearrangement_codes,
        dorp=_rearrangement_dorp,
        latent_model=_rearrangement_latent_model,
        # Blocks move one at a time: a block's move seen in one joint code of its group
        # is a move in the group's other joint codes too (CodeGraph.completed).
        graph_completion=True,
        draw_tasks=draw_grid_tasks,
        diagnostics=REARRANGEMENT_DIAGNOSTICS,
        description="k coloured 2x4 blocks on a 16x16 grid, moved one cell at a time",
    )
)
