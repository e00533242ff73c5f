"""Code diagnostics of k-object rearrangement against its true states (Figures 4(c), 5).

:func:`rearrangement_diagnostics` draws random configurations, moves one block a step and
measures how the codes follow the blocks (selectivity, purity, code maps over block
positions, temporal consistency); :func:`rearrangement_code_maps` maps codes over every
position of one block. :data:`REARRANGEMENT_DIAGNOSTICS` gives them to the env's profile
(:attr:`~dorp_rl.envs.EnvProfile.diagnostics`), through which the trainers log them and
the ``dorp`` command draws them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from dorp_rl.envs.grid_base import GRID_SIZE
from dorp_rl.envs.profile import CodeDiagnostics
from dorp_rl.metrics.diagnostics import (
    DEFAULT_CHUNK_SIZE,
    Encoder,
    best_assignment,
    connected_fraction,
    encode_states,
    fraction_true,
    majority_codes,
    mean_steps_random_pair,
    mean_steps_within_code,
)
from dorp_rl.validation import check_int, check_seed

if TYPE_CHECKING:
    from dorp_rl.envs.rearrangement import ObjectRearrangementEnv

__all__ = [
    "REARRANGEMENT_DIAGNOSTICS",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "rearrangement_pictures",
    "sample_rearrangement_states",
]

_MAX_REJECTION_ROUNDS = 10_000


def _check_env(env: Any) -> None:
    from dorp_rl.envs.rearrangement import ObjectRearrangementEnv  # it imports this module

    if not isinstance(env, ObjectRearrangementEnv):
        raise ValueError(
            f"env must be an ObjectRearrangementEnv, got {type(env).__name__}: these are "
            "the diagnostics of k-object rearrangement."
        )


def sample_rearrangement_states(
    env: ObjectRearrangementEnv, num: int, generator: torch.Generator
) -> torch.Tensor:
    """Random valid configurations, uniform over placements, from ``generator``.

    Same distribution as ``env.sample_states`` but without touching the env's own
    generator (diagnostics must not change what the env does next).

    Returns:
        int64 ``[num, k, 2]`` on the CPU: each block's top-left (row, column).
    """
    k = env.num_objects
    span = (GRID_SIZE - env.block_shapes.cpu() + 1).to(torch.float64)  # [k, 2]
    out = torch.empty((num, k, 2), dtype=torch.int64)
    todo = torch.arange(num)
    for _ in range(_MAX_REJECTION_ROUNDS):
        if todo.numel() == 0:
            break
        u = torch.rand((todo.numel(), k, 2), generator=generator, dtype=torch.float64)
        cand = (u * span).floor().to(torch.int64)
        ok = ~env.invalid_states(cand.to(env.device)).cpu()
        out[todo[ok]] = cand[ok]
        todo = todo[~ok]
    if todo.numel():
        raise RuntimeError(
            f"could not place {k} blocks without overlap in {_MAX_REJECTION_ROUNDS} rounds."
        )
    return out


def _single_object_moves(
    env: ObjectRearrangementEnv, states: torch.Tensor, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moves one random object of each configuration one valid step.

    The object is drawn uniformly, then the direction uniformly among its unblocked
    moves; configurations where the drawn object cannot move at all are skipped.

    Args:
        states: int64 ``[N, k, 2]``.

    Returns:
        ``movable`` bool ``[N]`` (configurations kept), ``moved`` int64 ``[M]`` (which
        object moved) and ``after`` int64 ``[M, k, 2]`` (configurations after the move).
    """
    n, k = states.shape[:2]
    obj = torch.randint(k, (n,), generator=generator)
    actions = obj[:, None] * 4 + torch.arange(4)  # [N, 4]
    nxt = env.transition(
        states[:, None].expand(n, 4, k, 2).to(env.device), actions.to(env.device)
    ).cpu()  # [N, 4, k, 2]
    can = (nxt != states[:, None]).flatten(2).any(-1)  # [N, 4]
    scores = torch.rand((n, 4), generator=generator).masked_fill(~can, -1.0)
    after = nxt[torch.arange(n), scores.argmax(-1)]
    movable = can.any(-1)
    return movable, obj[movable], after[movable]


def _position_grid(env: ObjectRearrangementEnv, obj: int) -> tuple[int, int]:
    """(rows, columns) of the grid of top-left positions of block ``obj`` (15 x 13 for 2x4)."""
    height, width = (int(v) for v in env.block_shapes[obj].tolist())
    return GRID_SIZE - height + 1, GRID_SIZE - width + 1


def rearrangement_diagnostics(
    env: ObjectRearrangementEnv,
    encode: Encoder,
    num_samples: int = 4096,
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> dict[str, Any]:
    """Object factorisation and temporal consistency of codes in k-object rearrangement.

    ``num_samples`` random configurations are drawn (from a generator seeded with
    ``seed``; the env's generator is left alone); in each, one random object moves one
    valid step (configurations where it cannot move are skipped), and both frames are
    encoded. Per-state measures (purity, code usage, maps, steps) use the ``num_samples``
    configurations before the moves.

    Args:
        env: the environment (its rules, renderer and block shapes are used).
        encode: ``encode(uint8 [n, 3, 16, 16]) -> int64 [n, C]``.
        num_samples: configurations to draw (at least 2).
        seed: seeds the configurations, the moves and the sampled pairs.
        chunk_size: frames per call of ``encode``.

    Returns:
        A JSON-serialisable dict (lists are per one-hot unless said otherwise; ``nan`` or
        ``None`` for one-hots with no assigned object):

        - ``num_objects`` k, ``num_onehots`` C, ``num_samples``, ``num_moves``;
        - ``selectivity``: share of one-hot changes on the moved object's own one-hot
          under ``assignment`` (``nan`` if no one-hot ever changed); chance ~ ``1 / C``;
        - ``assignment``: per object, its one-hot (``None`` if ``k > C`` leaves it out);
          ``onehot_object``: per one-hot, its object or ``None``;
        - ``change_matrix`` ``[k][C]``: moves of object o that changed one-hot c;
          ``moves_per_object`` ``[k]``; ``change_rate``: share of moves changing each
          one-hot;
        - ``frac_at_most_one_change``: share of moves changing at most one one-hot
          (the paper's Figure 4(c) view; weak on its own, see the module doc);
        - ``purity`` and ``min_purity`` (over assigned one-hots): majority-code accuracy
          of each one-hot's code given its object's (row, column);
        - ``codes_used`` (all one-hots) and ``min_codes_used`` (assigned ones): distinct
          codes over the sampled states;
        - ``connected_fraction`` / ``min_connected_fraction`` and ``num_map_codes``: on
          the grid of the assigned object's positions, each cell coloured by its majority
          code, the share of those codes whose cells are 4-connected;
        - ``mean_steps_within_code``: mean Manhattan distance between the object's
          positions in two states sharing the one-hot's code, and
          ``mean_steps_random_pair`` for two random states (the no-information baseline);
        - ``code_maps``: per one-hot the majority-code map ``[rows][cols]`` over its
          object's top-left positions (``-1`` = position not sampled), or ``None``.

    Raises:
        ValueError: bad ``env``/``num_samples``, or ``encode`` returns the wrong
            shape or dtype.
    """
    _check_env(env)
    num_samples = check_int("num_samples", num_samples, low=2)
    seed = check_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    k = env.num_objects
    states = sample_rearrangement_states(env, num_samples, generator)  # [N, k, 2]
    movable, moved, after = _single_object_moves(env, states, generator)
    codes = encode_states(env, encode, torch.cat([states, after]), chunk_size)
    state_codes, after_codes = codes[:num_samples], codes[num_samples:]
    num_onehots = codes.shape[1]

    changed = state_codes[movable] != after_codes  # [M, C]
    change_matrix = torch.zeros((k, num_onehots), dtype=torch.int64)
    change_matrix.index_add_(0, moved, changed.to(torch.int64))
    moves_per_object = torch.bincount(moved, minlength=k)
    assignment = best_assignment(change_matrix)
    total_changes = int(change_matrix.sum())
    matched = sum(int(change_matrix[o, c]) for o, c in enumerate(assignment) if c is not None)
    onehot_object: list[int | None] = [None] * num_onehots
    for o, c in enumerate(assignment):
        if c is not None:
            onehot_object[c] = o

    purity: list[float] = []
    codes_used: list[int] = []
    connected: list[float] = []
    num_map_codes: list[int | None] = []
    steps_within: list[float] = []
    steps_random: list[float] = []
    code_maps: list[list[list[int]] | None] = []
    for c, o in enumerate(onehot_object):
        codes_used.append(int(torch.unique(state_codes[:, c]).numel()))
        if o is None:
            purity.append(math.nan)
            connected.append(math.nan)
            num_map_codes.append(None)
            steps_within.append(math.nan)
            steps_random.append(math.nan)
            code_maps.append(None)
            continue
        rows, cols = _position_grid(env, o)
        positions = states[:, o]  # [N, 2]
        majority, accuracy = majority_codes(
            positions[:, 0] * cols + positions[:, 1], state_codes[:, c], rows * cols
        )
        code_map = majority.view(rows, cols)
        fraction, count = connected_fraction(code_map)
        purity.append(accuracy)
        connected.append(fraction)
        num_map_codes.append(count)
        steps_within.append(mean_steps_within_code(positions, state_codes[:, c], generator))
        steps_random.append(mean_steps_random_pair(positions, generator))
        code_maps.append(code_map.tolist())

    assigned = [c for c, o in enumerate(onehot_object) if o is not None]
    return {
        "env": type(env).__name__,
        "num_objects": k,
        "num_onehots": num_onehots,
        "num_samples": num_samples,
        "num_moves": len(moved),
        "seed": int(seed),
        "selectivity": matched / total_changes if total_changes else math.nan,
        "assignment": assignment,
        "onehot_object": onehot_object,
        "change_matrix": change_matrix.tolist(),
        "moves_per_object": moves_per_object.tolist(),
        "change_rate": (
            changed.double().mean(0).tolist() if len(moved) else [math.nan] * num_onehots
        ),
        "frac_at_most_one_change": fraction_true(changed.sum(-1) <= 1),
        "purity": purity,
        "min_purity": min((purity[c] for c in assigned), default=math.nan),
        "codes_used": codes_used,
        "min_codes_used": min((codes_used[c] for c in assigned), default=0),
        "connected_fraction": connected,
        "min_connected_fraction": min((connected[c] for c in assigned), default=math.nan),
        "num_map_codes": num_map_codes,
        "mean_steps_within_code": steps_within,
        "mean_steps_random_pair": steps_random,
        "code_maps": code_maps,
    }


def rearrangement_code_maps(
    env: ObjectRearrangementEnv,
    encode: Encoder,
    *,
    num_samples: int = 4096,
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> list[torch.Tensor | None]:
    """Per one-hot map of codes over block top-left positions (the paper's Figure 5).

    With one object every position is rendered once and the map is exact. With several,
    each assigned one-hot gets the majority code over its object's positions from
    :func:`rearrangement_diagnostics` (the other objects are random).

    Returns:
        Per one-hot an int64 ``[rows, cols]`` map (15 x 13 for 2x4 blocks; ``-1`` where no
        state was seen), or ``None`` for a one-hot with no assigned object.
    """
    _check_env(env)
    if env.num_objects == 1:
        rows, cols = _position_grid(env, 0)
        grid = torch.stack(
            torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij"), dim=-1
        )  # [rows, cols, 2]
        codes = encode_states(env, encode, grid.reshape(-1, 1, 2), chunk_size)  # [P, C]
        return [codes[:, c].view(rows, cols) for c in range(codes.shape[1])]
    result = rearrangement_diagnostics(env, encode, num_samples, seed, chunk_size)
    return [None if m is None else torch.tensor(m) for m in result["code_maps"]]


def _waypoint_maps(env: ObjectRearrangementEnv, encode: Encoder, result: Mapping[str, Any]) -> Any:
    """Exact maps over every position with one block, else ``result``'s majority maps."""
    return rearrangement_code_maps(env, encode) if env.num_objects == 1 else result


def rearrangement_pictures(
    env: ObjectRearrangementEnv, encode: Encoder, out_dir: Path, result: Mapping[str, Any]
) -> dict[str, Path]:
    """``code_map.png`` (exact map for 1 block, majority maps per one-hot otherwise) and
    ``factorization_histogram.png`` of ``result`` (:func:`rearrangement_diagnostics`) in
    ``out_dir``."""
    from dorp_rl.viz.code_maps import plot_code_maps, plot_factorization_histogram

    title = (
        f"{env.num_objects}-object rearrangement: selectivity {result['selectivity']:.2f}, "
        f"min purity {result['min_purity']:.2f}"
    )
    maps = _waypoint_maps(env, encode, result)
    return {
        "code_map": plot_code_maps(
            maps, out_dir / "code_map.png", title=title, axes=("block row", "block column")
        ),
        "factorization_histogram": plot_factorization_histogram(
            result, out_dir / "factorization_histogram.png"
        ),
    }


def _measure(env: ObjectRearrangementEnv, encode: Encoder, num_samples: int, seed: int) -> Any:
    return rearrangement_diagnostics(env, encode, num_samples=num_samples, seed=seed)


#: The rearrangement profile's diagnostics.
REARRANGEMENT_DIAGNOSTICS = CodeDiagnostics(
    measure=_measure, pictures=rearrangement_pictures, waypoint_maps=_waypoint_maps
)
