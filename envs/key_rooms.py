"""Key rooms: a one-pixel agent must fetch a one-pixel key to open a door."""

from __future__ import annotations

import torch

from dorp_rl.envs.grid_base import (
    DIRECTIONS,
    GRID_SIZE,
    GridWorldEnv,
    colour_codes,
    draw_grid_tasks,
    paint_layers,
)
from dorp_rl.envs.key_room_diagnostics import KEY_ROOM_DIAGNOSTICS
from dorp_rl.envs.profile import EnvProfile, register_env_profile

WALL_COLOUR = (128, 128, 128)  # grey
DOOR_COLOUR = (150, 75, 0)  # brown
KEY_COLOUR = (255, 255, 0)  # yellow
AGENT_COLOUR = (255, 0, 0)  # red

# Shortest-path tables per (layout, device): the same for every env of a layout.
_DISTANCE_CACHE: dict[tuple[str, str], torch.Tensor] = {}


def parse_layout(layout: str) -> dict[str, torch.Tensor]:
    """Reads an ASCII map (``#`` wall, ``D`` door, ``K`` key, ``.`` floor) of 16 x 16 cells."""
    lines = [line.strip() for line in layout.strip().splitlines()]
    if len(lines) != GRID_SIZE or any(len(line) != GRID_SIZE for line in lines):
        raise ValueError(f"a layout must be {GRID_SIZE} lines of {GRID_SIZE} characters.")
    if set("".join(lines)) - set("#DK."):
        raise ValueError("a layout may only use '#', 'D', 'K' and '.'.")
    chars = [list(line) for line in lines]
    grid = {
        c: torch.tensor([[ch == c for ch in row] for row in chars], dtype=torch.bool) for c in "#DK"
    }
    if int(grid["K"].sum()) != 1:
        raise ValueError("a layout needs exactly one key 'K'.")
    return {"wall": grid["#"], "door": grid["D"], "key": grid["K"]}


class KeyRoomEnv(GridWorldEnv):
    """Base of the key-room environments: one agent pixel, one key pixel, a locked door.

    ``state`` is int64 ``[*B, 3]``: agent row, agent column, has-key flag (0 or 1).
    The 4 actions move the agent up, down, left, right. Moving into a wall, a closed
    door or off the grid does nothing; stepping on the key takes it and opens the door.
    A random start puts the agent in an unlocked room without the key (not on the key);
    a random goal has the key taken, the door open and the agent on any free cell.

    Subclasses set :attr:`LAYOUT` (an ASCII map) and :attr:`DEFAULT_MAX_STEPS`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.envs import KeyWallEnv
        >>> env = KeyWallEnv(batch_size=(1,), seed=0)
        >>> start = TensorDict(state=torch.tensor([[0, 1, 0]]), batch_size=(1,))
        >>> td = env.reset(start, set_state=True)  # the agent just right of the key
        >>> td["action"] = torch.tensor([[2]])  # left, onto the key
        >>> env.step(td)["next", "state"].tolist()  # row, column, has-key
        [[0, 0, 1]]
    """

    LAYOUT: str = ""
    DEFAULT_MAX_STEPS: int = 400
    #: Length of the random walks of the paper's play data.
    PLAY_TRAJECTORY_LENGTH: int = 1000

    def __init__(self, *, max_steps: int | None = None, **kwargs) -> None:
        cells = parse_layout(self.LAYOUT)
        self._cells_cpu = cells
        super().__init__(
            max_steps=self.DEFAULT_MAX_STEPS if max_steps is None else max_steps, **kwargs
        )
        self.wall = cells["wall"].to(self.device)
        self.door = cells["door"].to(self.device)
        self.key = cells["key"].to(self.device)
        self.key_cell = self.key.nonzero()[0]  # [2]
        self.unlocked = self._reachable_without_key()
        free = ~self.wall
        # Flat indices (row * 16 + col) of valid starts and goals.
        self.start_cells = (self.unlocked & ~self.key).flatten().nonzero().squeeze(-1)
        self.goal_cells = free.flatten().nonzero().squeeze(-1)
        self._frame_table = self._build_frame_table()

    def oracle_layout(self) -> tuple[torch.Tensor, bool]:
        """What :class:`~dorp_rl.envs.OracleCodeEncoder` codes: the agent by the
        position of its colour, and a key bit (the key's colour gone from the frame)."""
        return torch.tensor([AGENT_COLOUR, KEY_COLOUR], dtype=torch.int64), True

    def config(self) -> dict:
        return {**super().config(), "layout": self.LAYOUT}

    @property
    def num_actions(self) -> int:
        return 4

    @property
    def state_shape(self) -> torch.Size:
        return torch.Size([3])

    def _state_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.zeros(3, dtype=torch.int64), torch.tensor([GRID_SIZE - 1, GRID_SIZE - 1, 1])

    def _reachable_without_key(self) -> torch.Tensor:
        """bool ``[16, 16]``: cells reachable from the key's room without crossing the door."""
        passable = ~self.wall & ~self.door
        reached = self.key.clone()
        while True:
            grown = reached.clone()
            grown[1:] |= reached[:-1]
            grown[:-1] |= reached[1:]
            grown[:, 1:] |= reached[:, :-1]
            grown[:, :-1] |= reached[:, 1:]
            grown &= passable
            if torch.equal(grown, reached):
                return reached
            reached = grown

    # ------------------------------------------------------------------ #
    def invalid_states(self, state: torch.Tensor) -> torch.Tensor:
        row, col, has_key = state.unbind(-1)
        off = (row < 0) | (row >= GRID_SIZE) | (col < 0) | (col >= GRID_SIZE)
        off |= (has_key < 0) | (has_key > 1)
        r, c = row.clamp(0, GRID_SIZE - 1), col.clamp(0, GRID_SIZE - 1)
        no_key = has_key == 0
        bad = self.wall[r, c] | (no_key & ~self.unlocked[r, c]) | (no_key & self.key[r, c])
        return off | bad

    def _describe_invalid(self, state: torch.Tensor, bad: torch.Tensor) -> str:
        return (
            "the agent must be on the grid and not in a wall, has-key must be 0 or 1, and "
            "without the key the agent must be in an unlocked room and not on the key"
        )

    def sample_states(self, shape: torch.Size) -> torch.Tensor:
        cell = self._sample_cells(self.start_cells, shape)
        return torch.stack([cell // GRID_SIZE, cell % GRID_SIZE, torch.zeros_like(cell)], dim=-1)

    def sample_goal_states(self, shape: torch.Size) -> torch.Tensor:
        cell = self._sample_cells(self.goal_cells, shape)
        return torch.stack([cell // GRID_SIZE, cell % GRID_SIZE, torch.ones_like(cell)], dim=-1)

    def _sample_cells(self, cells: torch.Tensor, shape: torch.Size) -> torch.Tensor:
        pick = torch.randint(len(cells), tuple(shape), generator=self.rng, device=self.device)
        return cells[pick]

    def transition(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        pos, has_key = state[..., :2], state[..., 2]
        target = pos + DIRECTIONS.to(state.device)[action]
        inside = ((target >= 0) & (target < GRID_SIZE)).all(-1)
        r, c = target.unbind(-1)
        r, c = r.clamp(0, GRID_SIZE - 1), c.clamp(0, GRID_SIZE - 1)
        blocked = ~inside | self.wall[r, c] | (self.door[r, c] & (has_key == 0))
        new_pos = torch.where(blocked.unsqueeze(-1), pos, target)
        on_key = (new_pos == self.key_cell).all(-1)
        new_key = torch.where(on_key, torch.ones_like(has_key), has_key)
        return torch.cat([new_pos, new_key.unsqueeze(-1)], dim=-1)

    def _all_states(self) -> torch.Tensor:
        """int64 ``[512, 3]``: every (row, col, has-key), ordered by :meth:`_state_index`."""
        idx = torch.arange(2 * GRID_SIZE * GRID_SIZE, device=self.device)
        cells = idx % (GRID_SIZE * GRID_SIZE)
        return torch.stack(
            [cells // GRID_SIZE, cells % GRID_SIZE, idx // (GRID_SIZE * GRID_SIZE)], -1
        )

    def _build_frame_table(self) -> torch.Tensor:
        """uint8 ``[512, 3, 16, 16]``: the frame of every (cell, has-key) state."""
        states = self._all_states()
        rows, cols = self._coords()
        closed = (states[:, 2] == 0).view(-1, 1, 1)
        agent = (rows == states[:, 0, None, None]) & (cols == states[:, 1, None, None])
        n = states.shape[0]
        masks = torch.stack(
            [
                self.wall.expand(n, GRID_SIZE, GRID_SIZE),
                self.door & closed,
                self.key & closed,
                agent,
            ],
            dim=-3,
        )
        colours = torch.tensor(
            [WALL_COLOUR, DOOR_COLOUR, KEY_COLOUR, AGENT_COLOUR],
            dtype=torch.uint8,
            device=self.device,
        )
        return paint_layers(masks, colours)

    def render_state(self, state: torch.Tensor) -> torch.Tensor:
        """Draws states ``[*B, 3]`` as uint8 ``[*B, 3, 16, 16]``: one gather per frame."""
        index = self._state_index(state.clamp(0, GRID_SIZE - 1)).reshape(-1)
        return self._frame_table.index_select(0, index).view(
            *state.shape[:-1], 3, GRID_SIZE, GRID_SIZE
        )

    def frame_parts(self, state: torch.Tensor) -> torch.Tensor:
        """int64 ``[*B, 1]``: each state's whole frame, a row of :meth:`frame_part_table`."""
        return self._state_index(state.clamp(0, GRID_SIZE - 1)).unsqueeze(-1)

    def frame_part_table(self) -> torch.Tensor:
        """uint8 ``[512, 3, 16, 16]``: the frame of every (cell, has-key) state."""
        return self._frame_table

    def states_from_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """int64 ``[*B, 3]``: the agent's pixel (first red pixel) and whether the key is gone."""
        codes = colour_codes(frames.to(self.device))  # [*B, 16, 16]
        agent = codes == colour_codes(torch.tensor(AGENT_COLOUR, dtype=torch.uint8).view(3, 1, 1))
        row = agent.any(-1).to(torch.int64).argmax(-1)
        col = agent.any(-2).to(torch.int64).argmax(-1)
        key_code = int(colour_codes(torch.tensor(KEY_COLOUR, dtype=torch.uint8).view(3, 1, 1)))
        key_row, key_col = (int(x) for x in self.key_cell)
        has_key = (codes[..., key_row, key_col] != key_code).to(torch.int64)
        return torch.stack([row, col, has_key], -1)

    # ------------------------------------------------------------------ #
    def _state_index(self, state: torch.Tensor) -> torch.Tensor:
        return state[..., 2] * GRID_SIZE * GRID_SIZE + state[..., 0] * GRID_SIZE + state[..., 1]

    def distance_table(self) -> torch.Tensor:
        """int64 ``[512, 512]``: exact shortest-path steps between all (cell, key) states.

        Entry ``[i, j]`` is ``-1`` when ``j`` cannot be reached from ``i`` (the key cannot
        be put back). Computed once per layout and device by breadth-first search from all
        sources at once, and shared by every env with that layout.
        """
        cache_key = (self.LAYOUT, str(self.device))
        if cache_key not in _DISTANCE_CACHE:
            states = self._all_states()
            n = states.shape[0]
            successors = [
                self._state_index(self.transition(states, torch.full((n,), a, device=self.device)))
                for a in range(4)
            ]
            dist = torch.full((n, n), -1, dtype=torch.int64, device=self.device)
            reached = torch.eye(n, dtype=torch.bool, device=self.device)  # [source, state]
            frontier = reached.to(torch.float32)
            dist[reached] = 0
            step = 0
            while True:
                step += 1
                grown = torch.zeros_like(frontier)
                for nxt in successors:  # push every frontier state to its successor
                    grown.index_add_(1, nxt, frontier)
                new = (grown > 0) & ~reached
                if not new.any():
                    break
                dist[new] = step
                reached |= new
                frontier = new.to(torch.float32)
            _DISTANCE_CACHE[cache_key] = dist
        return _DISTANCE_CACHE[cache_key]

    def _lower_bound_steps(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        """Exact BFS steps from ``state`` to ``goal_state`` (``-1`` if unreachable)."""
        return self.distance_table()[self._state_index(state), self._state_index(goal_state)]


class KeyWallEnv(KeyRoomEnv):
    """Key-wall: two rooms split by a wall at column 8 with a 3-cell door (rows 6-8).

    The key lies at (0, 0) in the left room; the right room is locked until it is taken.
    ``K`` key, ``D`` door, ``#`` wall::

        K.......#.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......
        ........D.......
        ........D.......
        ........D.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......
        ........#.......

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> env = KeyWallEnv(batch_size=(2,), seed=0)
        >>> env.reset()["state"][:, 2].tolist()  # starts without the key
        [0, 0]
    """

    LAYOUT = "\n".join(
        ["K.......#......."]
        + ["........#......."] * 5
        + ["........D......."] * 3
        + ["........#......."] * 7
    )
    DEFAULT_MAX_STEPS = 400


class KeyCorridorEnv(KeyRoomEnv):
    """Key-corridor: six rooms off a central corridor (columns 6-9); the top-right is locked.

    Vertical walls at columns 5 and 10 with openings, stubs at rows 5 and 10 split each
    side into three rooms, the key lies at (15, 0) in the bottom-left room and the door
    (rows 0-1 of column 10) is the only way into the top-right room::

        .....#....D.....
        .....#....D.....
        ..........#.....
        ..........#.....
        .....#....#.....
        ######....######
        .....#....#.....
        ................
        ................
        .....#....#.....
        ######....######
        .....#....#.....
        ................
        ................
        .....#....#.....
        K....#....#.....

    Examples:
        >>> from dorp_rl.envs import KeyCorridorEnv
        >>> env = KeyCorridorEnv(seed=0)
        >>> env.max_steps
        800
    """

    LAYOUT = "\n".join(
        [
            ".....#....D.....",
            ".....#....D.....",
            "..........#.....",
            "..........#.....",
            ".....#....#.....",
            "######....######",
            ".....#....#.....",
            "................",
            "................",
            ".....#....#.....",
            "######....######",
            ".....#....#.....",
            "................",
            "................",
            ".....#....#.....",
            "K....#....#.....",
        ]
    )
    DEFAULT_MAX_STEPS = 800
    PLAY_TRAJECTORY_LENGTH = 1500


#: The key rooms' code recipe: 4-step pairs from long random walks, an agent one-hot plus
#: a key bit, with motion, sparsity and usage terms (docs/NOTES.md has the measurements).
KEY_ROOM_RECIPE: dict = {
    "max_offset": 4,
    "motion_weight": 1.0,
    "sparsity_weight": 5.0,
    "usage_weight": 1.0,
    "num_steps": 3000,
    "collapse_check_after": 500,
    "collapse_min_codes": 4,
}


def _key_room_profile(
    name: str,
    env_type: type[KeyRoomEnv],
    agent_codes: int,
    num_frames: int,
    world_model: dict,
    description: str,
) -> EnvProfile:
    return EnvProfile(
        name=name,
        make_env=env_type,
        env_type=env_type,
        play_trajectory_length=env_type.PLAY_TRAJECTORY_LENGTH,
        max_steps=env_type.DEFAULT_MAX_STEPS,
        code_layout=lambda size, _: (size, 2),
        codes=lambda _: {
            # Measured on the frames as they are (walls and door included).
            "encoder": {"code_sizes": (agent_codes,), "subtract_background": False},
            "num_frames": num_frames,
            **KEY_ROOM_RECIPE,
        },
        world_model=lambda _: {"trajectory_length": env_type.PLAY_TRAJECTORY_LENGTH, **world_model},
        # The default latent model with more play data; a quarter of its windows hold
        # a key event (the default where the codes show one), without which
        # key-corridor's model never imagined the key taken.
        latent_model=lambda _: {"num_frames": 100_000, "num_steps": 3000},
        groups=((0, 1),),
        # Re-enter a code another way, replan after a miss, no goal-image term in the
        # waypoint cost (pixel distance ignores the walls). A latent model's goal-image
        # phase judges decoded frames: the agent is one pixel, and the imagined latents
        # one step from the goal did not tell its neighbouring cells apart (the phase
        # went back and forth between two cells). docs/NOTES.md has the figures.
        dorp={
            "reenter": True,
            "replan_on_miss": True,
            "waypoint_goal_weight": 0.0,
            "goal_latent_weight": 0.0,
        },
        draw_tasks=draw_grid_tasks,
        diagnostics=KEY_ROOM_DIAGNOSTICS,
        description=description,
    )


#: The key rooms as the pipeline sees them (``--env key-wall``, ``--env key-corridor``).
KEY_WALL = register_env_profile(
    # Key events are rare in play: a quarter of the world model's training windows hold
    # one (docs/NOTES.md, key-wall through the video model).
    _key_room_profile(
        "key-wall", KeyWallEnv, 16, 64_000, {"event_share": 0.25}, "one room behind a locked door"
    )
)
KEY_CORRIDOR = register_env_profile(
    _key_room_profile(
        "key-corridor", KeyCorridorEnv, 32, 96_000, {}, "rooms along a corridor, one locked door"
    )
)
