"""Code diagnostics of the key rooms against their true states (Figure 6).

:func:`key_room_diagnostics` enumerates every key event and agent move of a key-wall or
key-corridor env and measures how the codes follow them (the key one-hot on key events,
the agent one-hot on moves, agent code maps without and with the key, temporal
consistency); :func:`plot_key_room_code_map` draws the maps over the room.
:data:`KEY_ROOM_DIAGNOSTICS` gives them to the envs' profiles
(:attr:`~dorp_rl.envs.EnvProfile.diagnostics`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from dorp_rl.envs.grid_base import GRID_SIZE
from dorp_rl.envs.profile import CodeDiagnostics
from dorp_rl.metrics.diagnostics import (
    DEFAULT_CHUNK_SIZE,
    Encoder,
    connected_fraction,
    encode_states,
    fraction_true,
)

if TYPE_CHECKING:
    from dorp_rl.envs.key_rooms import KeyRoomEnv

__all__ = [
    "KEY_ROOM_DIAGNOSTICS",
    "key_event_states",
    "key_room_code_maps",
    "key_room_diagnostics",
    "key_room_pictures",
    "plot_key_room_code_map",
]


def _check_env(env: Any) -> None:
    from dorp_rl.envs.key_rooms import KeyRoomEnv  # it imports this module

    if not isinstance(env, KeyRoomEnv):
        raise ValueError(
            f"env must be a KeyRoomEnv (KeyWallEnv, KeyCorridorEnv), got {type(env).__name__}."
        )


def _cells_to_states(cells: torch.Tensor, has_key: int) -> torch.Tensor:
    """Flat cell indices ``[n]`` -> key-room states int64 ``[n, 3]``."""
    cells = cells.cpu()
    return torch.stack(
        [cells // GRID_SIZE, cells % GRID_SIZE, torch.full_like(cells, has_key)], dim=-1
    )


def key_event_states(env: KeyRoomEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """The key events of :func:`key_room_diagnostics`: states int64 ``[E, 3]`` of every
    start-able cell without the key, and the same cells with it, in the same order."""
    start_cells = env.start_cells.cpu()
    return _cells_to_states(start_cells, 0), _cells_to_states(start_cells, 1)


def _code_map(cells: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """int64 ``[16, 16]`` map with ``codes[i]`` at flat cell ``cells[i]``, ``-1`` elsewhere."""
    out = torch.full((GRID_SIZE * GRID_SIZE,), -1, dtype=torch.int64)
    out[cells.cpu()] = codes
    return out.view(GRID_SIZE, GRID_SIZE)


def _mean_exact_steps(
    env: KeyRoomEnv, states: torch.Tensor, codes: torch.Tensor
) -> tuple[float, float]:
    """Mean exact steps between all ordered pairs of distinct reachable states: those
    sharing a code, and all of them (the baseline). ``states`` ``[n, 3]``, ``codes`` ``[n]``."""
    n = len(states)
    s = states.to(env.device)
    dist = env.lower_bound_steps(s[:, None].expand(n, n, 3), s[None].expand(n, n, 3)).cpu()
    ok = (dist >= 0) & ~torch.eye(n, dtype=torch.bool)
    same = ok & (codes[:, None] == codes[None, :])
    within = float(dist[same].double().mean()) if same.any() else math.nan
    baseline = float(dist[ok].double().mean()) if ok.any() else math.nan
    return within, baseline


def key_room_diagnostics(
    env: KeyRoomEnv,
    encode: Encoder,
    key_onehot: int | None = None,
    agent_onehot: int | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    with_steps: bool = True,
) -> dict[str, Any]:
    """Key/agent factorisation and temporal consistency of codes in key-wall/key-corridor.

    Everything is enumerated exactly (no sampling):

    - key events (the paper's Figure 6(c)): every start-able cell (unlocked, not the key)
      without the key, and the same cell with has-key flipped to 1;
    - agent moves (Figure 6(d)): every valid state and action that moves the agent
      without taking the key;
    - code maps of the agent one-hot without the key (unlocked cells) and with it (all
      free cells), as in Figure 6(a, b).

    Args:
        env: a :class:`~dorp_rl.envs.KeyRoomEnv` (its exact BFS distances are used).
        encode: ``encode(uint8 [n, 3, 16, 16]) -> int64 [n, C]`` with ``C >= 2``.
        key_onehot: the key one-hot; by default the one that changes most on key events.
        agent_onehot: the agent one-hot; by default the other one that changes most on
            agent moves.
        chunk_size: frames per call of ``encode``.
        with_steps: compute the mean-steps numbers. They need the env's exact distance
            table (one BFS over all 512 states, a few seconds the first time per env
            instance); ``False`` reports them as ``nan``.

    Returns:
        A JSON-serialisable dict:

        - ``num_onehots``, ``key_onehot``, ``agent_onehot``, ``num_key_events``,
          ``num_moves``;
        - ``key_bit_change_fraction``: share of key events changing the key one-hot;
        - ``agent_onehot_unchanged_fraction``: share of key events where every one-hot
          other than the key one-hot stays the same;
        - ``move_selectivity``: share of agent moves (key untouched) that leave the key
          one-hot unchanged; ``move_agent_change_fraction``: share that change the agent
          one-hot;
        - ``codes_used_without_key`` / ``_with_key`` / ``codes_used`` (both): distinct
          agent codes; ``key_codes_used``: distinct key-one-hot codes over all states;
        - ``connected_fraction_without_key`` / ``_with_key``: share of agent codes whose
          cells are 4-connected on the map;
        - ``mean_steps_within_code_without_key`` / ``_with_key``: exact mean steps between
          two distinct states sharing the agent code, next to
          ``mean_steps_random_pair_without_key`` / ``_with_key`` for any two states;
        - ``change_matrix`` ``[2][C]``: one-hot changes on key events (row 0) and agent
          moves (row 1), with ``change_totals`` ``[2]``;
        - ``code_map_without_key`` / ``code_map_with_key``: ``[16][16]`` agent codes,
          ``-1`` on cells that are not valid in that condition.

    Raises:
        ValueError: bad env, fewer than 2 one-hots, a one-hot index out of range, or a
            wrong encoder output.
    """
    _check_env(env)
    start_cells, free_cells = env.start_cells.cpu(), env.goal_cells.cpu()
    without_key = _cells_to_states(start_cells, 0)  # [E, 3]
    with_key = _cells_to_states(free_cells, 1)  # [F, 3]
    codes = encode_states(env, encode, torch.cat([without_key, with_key]), chunk_size)
    num_onehots = codes.shape[1]
    if num_onehots < 2:
        raise ValueError(
            f"key_room_diagnostics needs at least 2 one-hots (agent and key); encode gave {num_onehots}."
        )
    codes_without, codes_with = codes[: len(without_key)], codes[len(without_key) :]

    # Codes of every valid state, looked up by has_key * 256 + row * 16 + col.
    table = torch.full((2 * GRID_SIZE * GRID_SIZE, num_onehots), -1, dtype=torch.int64)
    table[start_cells] = codes_without
    table[GRID_SIZE * GRID_SIZE + free_cells] = codes_with

    def index(states: torch.Tensor) -> torch.Tensor:
        return states[:, 2] * GRID_SIZE * GRID_SIZE + states[:, 0] * GRID_SIZE + states[:, 1]

    # Key events: same cell, has-key 0 -> 1.
    key_event_changed = codes_without != table[index(without_key) + GRID_SIZE * GRID_SIZE]

    # Agent moves that do not touch the key.
    valid = torch.cat([without_key, with_key])
    n = len(valid)
    actions = torch.arange(4).repeat(n)
    sources = valid.repeat_interleave(4, dim=0)
    targets = env.transition(sources.to(env.device), actions.to(env.device)).cpu()
    is_move = (targets[:, :2] != sources[:, :2]).any(-1) & (targets[:, 2] == sources[:, 2])
    move_changed = table[index(sources[is_move])] != table[index(targets[is_move])]

    for name, value in (("key_onehot", key_onehot), ("agent_onehot", agent_onehot)):
        if value is not None and not 0 <= value < num_onehots:
            raise ValueError(f"{name} must be in [0, {num_onehots - 1}], got {value}.")
    if key_onehot is None:
        key_onehot = int(key_event_changed.double().mean(0).argmax())
    if agent_onehot is None:
        rates = move_changed.double().mean(0)
        rates[key_onehot] = -1.0
        agent_onehot = int(rates.argmax())
    if agent_onehot == key_onehot:
        raise ValueError(f"agent_onehot and key_onehot must differ, both are {key_onehot}.")
    others = [c for c in range(num_onehots) if c != key_onehot]

    agent_without, agent_with = codes_without[:, agent_onehot], codes_with[:, agent_onehot]
    map_without = _code_map(start_cells, agent_without)
    map_with = _code_map(free_cells, agent_with)
    connected_without, _ = connected_fraction(map_without)
    connected_with, _ = connected_fraction(map_with)
    steps_without = random_without = steps_with = random_with = math.nan
    if with_steps:
        steps_without, random_without = _mean_exact_steps(env, without_key, agent_without)
        steps_with, random_with = _mean_exact_steps(env, with_key, agent_with)
    change_matrix = torch.stack(
        [key_event_changed.sum(0), move_changed.sum(0)]
    )  # [2, C]: key events, agent moves
    return {
        "env": type(env).__name__,
        "num_onehots": num_onehots,
        "key_onehot": key_onehot,
        "agent_onehot": agent_onehot,
        "num_key_events": len(key_event_changed),
        "num_moves": len(move_changed),
        "key_bit_change_fraction": fraction_true(key_event_changed[:, key_onehot]),
        "agent_onehot_unchanged_fraction": fraction_true(~key_event_changed[:, others].any(-1)),
        "move_selectivity": fraction_true(~move_changed[:, key_onehot]),
        "move_agent_change_fraction": fraction_true(move_changed[:, agent_onehot]),
        "codes_used_without_key": int(torch.unique(agent_without).numel()),
        "codes_used_with_key": int(torch.unique(agent_with).numel()),
        "codes_used": int(torch.unique(torch.cat([agent_without, agent_with])).numel()),
        "key_codes_used": int(torch.unique(codes[:, key_onehot]).numel()),
        "connected_fraction_without_key": connected_without,
        "connected_fraction_with_key": connected_with,
        "mean_steps_within_code_without_key": steps_without,
        "mean_steps_within_code_with_key": steps_with,
        "mean_steps_random_pair_without_key": random_without,
        "mean_steps_random_pair_with_key": random_with,
        "change_matrix": change_matrix.tolist(),
        "change_totals": [len(key_event_changed), len(move_changed)],
        "code_map_without_key": map_without.tolist(),
        "code_map_with_key": map_with.tolist(),
    }


def key_room_code_maps(
    env: KeyRoomEnv,
    encode: Encoder,
    agent_onehot: int | None = None,
    key_onehot: int | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The agent one-hot's codes over cells, without and with the key (Figure 6(a, b)).

    Returns:
        Two int64 ``[16, 16]`` maps, ``-1`` on cells not valid in that condition (walls,
        the locked room and the key cell without the key; walls with it).
    """
    result = key_room_diagnostics(
        env, encode, key_onehot, agent_onehot, chunk_size, with_steps=False
    )
    return torch.tensor(result["code_map_without_key"]), torch.tensor(result["code_map_with_key"])


def plot_key_room_code_map(
    env: KeyRoomEnv,
    codes_without_key: torch.Tensor | np.ndarray,
    codes_with_key: torch.Tensor | np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    annotate: bool = True,
) -> Path:
    """The agent one-hot's codes over cells without and with the key (Figure 6(a, b)).

    Walls are black; cells that are not valid in a panel's condition (the locked room
    and the key cell without the key) are white; the key cell and the door are outlined.

    Args:
        env: the key-room environment (walls, key and door are read from it).
        codes_without_key: int ``[16, 16]`` agent codes, ``-1`` on invalid cells.
        codes_with_key: int ``[16, 16]`` agent codes, ``-1`` on invalid cells.
        path: PNG file to write.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from dorp_rl.viz.code_maps import (
        WALL_COLOUR,
        as_code_array,
        code_colours,
        draw_code_map,
        save_figure,
    )

    wall = env.wall.cpu().numpy()
    key_cell = env.key.cpu().numpy().nonzero()
    door_cells = np.argwhere(env.door.cpu().numpy())
    fig = Figure(figsize=(7.6, 4.0))
    for i, (codes, name) in enumerate(
        ((codes_without_key, "without key"), (codes_with_key, "with key"))
    ):
        codes = as_code_array(codes)
        if codes.shape != wall.shape:
            raise ValueError(f"code maps must be {list(wall.shape)}, got {list(codes.shape)}.")
        rgb = code_colours(codes)
        rgb[wall] = WALL_COLOUR
        ax = fig.add_subplot(1, 2, i + 1)
        used = len(np.unique(codes[codes >= 0]))
        draw_code_map(ax, codes, rgb, f"agent codes {name}: {used} codes", annotate)
        ax.add_patch(
            Rectangle(
                (key_cell[1][0] - 0.5, key_cell[0][0] - 0.5), 1, 1, fill=False, ec="gold", lw=2
            )
        )
        for r, c in door_cells:
            ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, ec="saddlebrown", lw=1.5))
        ax.set_xlabel("column", fontsize=8)
        if i == 0:
            ax.set_ylabel("row", fontsize=8)
    fig.suptitle(title or f"{type(env).__name__}: agent one-hot", fontsize=10)
    return save_figure(fig, path)


def key_room_pictures(
    env: KeyRoomEnv, encode: Encoder, out_dir: Path, result: Mapping[str, Any]
) -> dict[str, Path]:
    """``code_map.png`` (agent codes without / with the key) and
    ``factorization_histogram.png`` (one-hot changes on key events and agent moves) of
    ``result`` (:func:`key_room_diagnostics`) in ``out_dir``."""
    from dorp_rl.viz.code_maps import plot_factorization_histogram

    return {
        "code_map": plot_key_room_code_map(
            env,
            result["code_map_without_key"],
            result["code_map_with_key"],
            out_dir / "code_map.png",
        ),
        "factorization_histogram": plot_factorization_histogram(
            result,
            out_dir / "factorization_histogram.png",
            title="one-hots changed on key events and agent moves (hatched: expected)",
        ),
    }


def _measure(env: KeyRoomEnv, encode: Encoder, num_samples: int, seed: int) -> Any:
    return key_room_diagnostics(env, encode)  # exact: every state, no sampling


def _waypoint_maps(env: KeyRoomEnv, encode: Encoder, result: Mapping[str, Any]) -> Any:
    return result  # the agent one-hot's maps without and with the key


#: The key rooms' profiles' diagnostics.
KEY_ROOM_DIAGNOSTICS = CodeDiagnostics(
    measure=_measure, pictures=key_room_pictures, waypoint_maps=_waypoint_maps
)
