"""Code-quality diagnostics of discrete object codes, measured against ground-truth states.

DORP's planner is only as good as its codes: one one-hot per object, each changing only
when its own object moves, and each code covering a compact, connected patch of that
object's positions. The functions here measure exactly that from the environments' true
states, for any encoder given as a plain callable::

    encode(pixels: uint8 [N, 3, 16, 16]) -> int64 [N, C]   # one code index per one-hot

(the encoder's ``argmax`` codes). It is called in chunks under :func:`torch.no_grad`.

Why not just the paper's Figure 4(c) number (the fraction of single-object moves that
change at most one one-hot)? Each one-hot changes on only 15-25% of moves, so an
untrained or fully entangled encoder already scores ~0.97 on it. It is reported, but
the numbers that separate good codes from bad ones are:

- **selectivity**: of all one-hot changes caused by moving one object, the share that land
  on that object's own one-hot, under the best object-to-one-hot assignment (chance is
  about ``1 / C``: 0.5 for 2 objects);
- **purity**: how well the assigned object's own position predicts a one-hot's code
  (majority-code accuracy over states grouped by that position);
- **temporal consistency**: the share of codes whose positions form one 4-connected
  region, and the mean number of steps between two states that share a code.

:func:`rearrangement_diagnostics` and :func:`key_room_diagnostics` return everything as
JSON-serialisable dicts (plain ``int``/``float``/``list``/``None``; undefined numbers are
``nan``). :mod:`dorp_rl.viz.code_maps` turns them into the paper's pictures.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from dorp_rl.envs.grid_base import GRID_SIZE
from dorp_rl.envs.key_rooms import KeyRoomEnv
from dorp_rl.envs.rearrangement import ObjectRearrangementEnv
from dorp_rl.frames import check_frames
from dorp_rl.validation import check_int, check_seed

#: ``encode(pixels uint8 [N, 3, 16, 16]) -> int64 [N, C]``: one code index per one-hot.
Encoder = Callable[[torch.Tensor], torch.Tensor]

DEFAULT_CHUNK_SIZE = 4096
_MAX_REJECTION_ROUNDS = 10_000
#: The exact assignment search keeps one entry per subset of the larger side.
_MAX_ASSIGNMENT_SIDE = 20

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "Encoder",
    "GROUND_TRUTH_DIAGNOSTICS",
    "best_assignment",
    "connected_fraction",
    "encode_pixels",
    "ground_truth_diagnostics",
    "key_room_code_maps",
    "key_room_diagnostics",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "sample_rearrangement_states",
]


# ---------------------------------------------------------------------- #
# Encoding
# ---------------------------------------------------------------------- #
def _describe(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {value.dtype} tensor of shape {list(value.shape)}"
    return f"a {type(value).__name__}"


def encode_pixels(
    encode: Encoder, pixels: torch.Tensor, chunk_size: int = DEFAULT_CHUNK_SIZE
) -> torch.Tensor:
    """Encodes frames in chunks under ``torch.no_grad()`` and checks what comes back.

    Args:
        encode: ``encode(uint8 [n, 3, 16, 16]) -> int64 [n, C]``.
        pixels: uint8 ``[N, 3, 16, 16]``.
        chunk_size: frames per call of ``encode``.

    Returns:
        int64 ``[N, C]`` on the CPU.

    Raises:
        ValueError: if ``pixels`` is not uint8 ``[N, 3, 16, 16]``, or ``encode`` returns
            anything but an int64 ``[n, C]`` tensor of non-negative code indices with the
            same ``C`` for every chunk.
    """
    pixels = check_frames(pixels, "pixels", lead="N", shape=(3, GRID_SIZE, GRID_SIZE))
    chunk_size = check_int("chunk_size", chunk_size, low=1)
    if len(pixels) == 0:
        raise ValueError("pixels is empty: nothing to encode.")
    outputs: list[torch.Tensor] = []
    num_onehots: int | None = None
    with torch.no_grad():
        for start in range(0, len(pixels), chunk_size):
            chunk = pixels[start : start + chunk_size]
            codes = encode(chunk)
            expected = (
                f"encode must return an int64 tensor of shape [N, C] = [{len(chunk)}, "
                f"{'C' if num_onehots is None else num_onehots}] (one code index per one-hot) "
                f"for pixels of shape {list(chunk.shape)}"
            )
            if not isinstance(codes, torch.Tensor) or codes.dtype != torch.int64:
                raise ValueError(f"{expected}; got {_describe(codes)}.")
            if codes.dim() != 2 or codes.shape[0] != len(chunk) or codes.shape[1] < 1:
                raise ValueError(f"{expected}; got shape {list(codes.shape)}.")
            if num_onehots is not None and codes.shape[1] != num_onehots:
                raise ValueError(f"{expected}; got shape {list(codes.shape)}.")
            if (codes < 0).any():
                raise ValueError(f"{expected}, with code indices >= 0; got negative indices.")
            num_onehots = codes.shape[1]
            outputs.append(codes.detach().cpu())
    return torch.cat(outputs)


def _encode_states(
    env: ObjectRearrangementEnv | KeyRoomEnv,
    encode: Encoder,
    states: torch.Tensor,
    chunk_size: int,
) -> torch.Tensor:
    """Renders ``[N, *state_shape]`` states in chunks and encodes them: int64 ``[N, C]``."""
    codes = []
    for start in range(0, len(states), chunk_size):
        chunk = states[start : start + chunk_size].to(env.device)
        codes.append(encode_pixels(encode, env.render_state(chunk), chunk_size))
    if len({c.shape[1] for c in codes}) > 1:
        raise ValueError(
            "encode must return the same number of one-hots C for every call; got "
            f"{sorted({c.shape[1] for c in codes})}."
        )
    return torch.cat(codes)


# ---------------------------------------------------------------------- #
# Generic measures
# ---------------------------------------------------------------------- #
def best_assignment(matrix: torch.Tensor | np.ndarray | Sequence[Sequence[float]]) -> list:
    """Injective row-to-column assignment maximising the sum of the matched entries.

    Used to match objects (rows) to one-hots (columns) by how often a one-hot changes
    when an object moves. Exact: dynamic programming over subsets of the columns
    (``O(R * K * 2^K)``), so up to 20 on the larger side. Ties are broken
    deterministically.

    Args:
        matrix: ``[R, K]`` scores.

    Returns:
        A list of length ``R``: the column of each row. When ``R > K`` only ``K`` rows get
        a column and the others get ``None``.

    Examples:
        >>> from dorp_rl.metrics import best_assignment
        >>> best_assignment([[0.1, 0.9], [0.8, 0.3]])  # object 0 -> one-hot 1, 1 -> 0
        [1, 0]
    """
    scores = np.asarray(
        matrix.detach().cpu().numpy() if isinstance(matrix, torch.Tensor) else matrix,
        dtype=np.float64,
    )
    if scores.ndim != 2:
        raise ValueError(f"matrix must be 2-D [rows, columns], got shape {list(scores.shape)}.")
    rows, cols = scores.shape
    if rows > cols:
        inverse = best_assignment(scores.T)
        out: list[int | None] = [None] * rows
        for col, row in enumerate(inverse):
            out[row] = col
        return out
    if cols > _MAX_ASSIGNMENT_SIDE:
        raise ValueError(
            f"best_assignment searches all subsets of the larger side; {cols} > "
            f"{_MAX_ASSIGNMENT_SIDE} is too many."
        )
    if rows == 0:
        return []
    masks = np.arange(1 << cols)
    value = np.full(1 << cols, -np.inf)
    value[0] = 0.0
    choice = np.full((rows, 1 << cols), -1, dtype=np.int64)
    for r in range(rows):
        new = np.full(1 << cols, -np.inf)
        for c in range(cols):
            bit = 1 << c
            src = masks[((masks & bit) == 0) & np.isfinite(value)]
            cand = value[src] + scores[r, c]
            dst = src | bit
            better = cand >= new[dst]
            new[dst[better]] = cand[better]
            choice[r, dst[better]] = c
        value = new
    mask = int(np.argmax(value))
    assignment = [0] * rows
    for r in reversed(range(rows)):
        c = int(choice[r, mask])
        assignment[r] = c
        mask ^= 1 << c
    return assignment


def _is_4_connected(mask: torch.Tensor) -> bool:
    """Whether the True cells of a bool ``[H, W]`` mask form one 4-connected region."""
    cells = mask.nonzero()
    if len(cells) <= 1:
        return True
    reached = torch.zeros_like(mask)
    reached[cells[0, 0], cells[0, 1]] = True
    while True:
        grown = reached.clone()
        grown[1:] |= reached[:-1]
        grown[:-1] |= reached[1:]
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown &= mask
        if torch.equal(grown, reached):
            return bool(torch.equal(reached, mask))
        reached = grown


def connected_fraction(code_map: torch.Tensor) -> tuple[float, int]:
    """Share of codes whose cells form one 4-connected region on a map.

    Args:
        code_map: int64 ``[H, W]``, a code per cell (``-1`` for cells without one: walls,
            invalid or unseen positions; they connect nothing).

    Returns:
        ``(fraction, number_of_codes)``; the fraction is ``nan`` when the map has no code.

    Examples:
        >>> import torch
        >>> from dorp_rl.metrics import connected_fraction
        >>> code_map = torch.tensor([[0, 0, 1, 1], [0, 2, 1, 1], [2, 2, 0, -1]])
        >>> connected_fraction(code_map)  # code 0 is split in two regions
        (0.6666666666666666, 3)
    """
    codes = torch.unique(code_map[code_map >= 0])
    if len(codes) == 0:
        return math.nan, 0
    connected = sum(_is_4_connected(code_map == code) for code in codes.tolist())
    return connected / len(codes), len(codes)


def _majority_codes(
    groups: torch.Tensor, codes: torch.Tensor, num_groups: int
) -> tuple[torch.Tensor, float]:
    """Majority code per group and the accuracy of predicting each code by it.

    Args:
        groups: int64 ``[N]`` in ``[0, num_groups)``.
        codes: int64 ``[N]``.
        num_groups: number of groups.

    Returns:
        int64 ``[num_groups]`` majority codes (``-1`` for empty groups; ties go to the
        smaller code) and the share of items whose code is their group's majority.
    """
    values, index = torch.unique(codes, return_inverse=True)
    counts = torch.bincount(groups * len(values) + index, minlength=num_groups * len(values)).view(
        num_groups, len(values)
    )
    best, arg = counts.max(dim=1)
    majority = torch.where(counts.sum(1) > 0, values[arg], torch.full_like(arg, -1))
    return majority, float(best.sum()) / max(len(codes), 1)


def _mean_steps_within_code(
    positions: torch.Tensor, codes: torch.Tensor, generator: torch.Generator
) -> float:
    """Mean Manhattan distance between a random state and a random other state of its code.

    Args:
        positions: int64 ``[N, 2]`` (row, column) of the object the one-hot is assigned to.
        codes: int64 ``[N]`` that one-hot's codes.
        generator: picks the partners.

    Returns:
        The mean over states whose code has at least two states (``nan`` if none). Codes
        are weighted by how many states carry them, as in a random pair of states.
    """
    n = len(codes)
    order = torch.argsort(codes, stable=True)
    _, counts = torch.unique_consecutive(codes[order], return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    group = torch.repeat_interleave(torch.arange(len(counts)), counts)  # per sorted slot
    size = counts[group]
    keep = size > 1
    if not keep.any():
        return math.nan
    rank = torch.arange(n) - starts[group]
    offset = (torch.rand(n, generator=generator, dtype=torch.float64) * (size - 1)).long()
    partner = starts[group] + offset + (offset >= rank).long()  # any member but itself
    first, second = order[keep], order[partner[keep]]
    return float((positions[first] - positions[second]).abs().sum(-1).double().mean())


def _mean_steps_random_pair(positions: torch.Tensor, generator: torch.Generator) -> float:
    """Baseline for :func:`_mean_steps_within_code`: Manhattan distance of random pairs."""
    partner = torch.randperm(len(positions), generator=generator)
    return float((positions - positions[partner]).abs().sum(-1).double().mean())


def _fraction(mask: torch.Tensor) -> float:
    return float(mask.double().mean()) if mask.numel() else math.nan


# ---------------------------------------------------------------------- #
# Rearrangement
# ---------------------------------------------------------------------- #
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
    if not isinstance(env, ObjectRearrangementEnv):
        raise ValueError(
            f"env must be an ObjectRearrangementEnv, got {type(env).__name__} "
            "(key rooms: use key_room_diagnostics)."
        )
    num_samples = check_int("num_samples", num_samples, low=2)
    seed = check_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    k = env.num_objects
    states = sample_rearrangement_states(env, num_samples, generator)  # [N, k, 2]
    movable, moved, after = _single_object_moves(env, states, generator)
    codes = _encode_states(env, encode, torch.cat([states, after]), chunk_size)
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
        majority, accuracy = _majority_codes(
            positions[:, 0] * cols + positions[:, 1], state_codes[:, c], rows * cols
        )
        code_map = majority.view(rows, cols)
        fraction, count = connected_fraction(code_map)
        purity.append(accuracy)
        connected.append(fraction)
        num_map_codes.append(count)
        steps_within.append(_mean_steps_within_code(positions, state_codes[:, c], generator))
        steps_random.append(_mean_steps_random_pair(positions, generator))
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
        "frac_at_most_one_change": _fraction(changed.sum(-1) <= 1),
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
    if not isinstance(env, ObjectRearrangementEnv):
        raise ValueError(f"env must be an ObjectRearrangementEnv, got {type(env).__name__}.")
    if env.num_objects == 1:
        rows, cols = _position_grid(env, 0)
        grid = torch.stack(
            torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij"), dim=-1
        )  # [rows, cols, 2]
        codes = _encode_states(env, encode, grid.reshape(-1, 1, 2), chunk_size)  # [P, C]
        return [codes[:, c].view(rows, cols) for c in range(codes.shape[1])]
    result = rearrangement_diagnostics(env, encode, num_samples, seed, chunk_size)
    return [None if m is None else torch.tensor(m) for m in result["code_maps"]]


# ---------------------------------------------------------------------- #
# Key rooms
# ---------------------------------------------------------------------- #
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
    if not isinstance(env, KeyRoomEnv):
        raise ValueError(
            f"env must be a KeyRoomEnv (KeyWallEnv, KeyCorridorEnv), got {type(env).__name__}."
        )
    start_cells, free_cells = env.start_cells.cpu(), env.goal_cells.cpu()
    without_key = _cells_to_states(start_cells, 0)  # [E, 3]
    with_key = _cells_to_states(free_cells, 1)  # [F, 3]
    codes = _encode_states(env, encode, torch.cat([without_key, with_key]), chunk_size)
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
        "key_bit_change_fraction": _fraction(key_event_changed[:, key_onehot]),
        "agent_onehot_unchanged_fraction": _fraction(~key_event_changed[:, others].any(-1)),
        "move_selectivity": _fraction(~move_changed[:, key_onehot]),
        "move_agent_change_fraction": _fraction(move_changed[:, agent_onehot]),
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


def _rearrangement(env: Any, encode: Encoder, num_samples: int, seed: int) -> Any:
    return rearrangement_diagnostics(env, encode, num_samples=num_samples, seed=seed)


def _key_room(env: Any, encode: Encoder, num_samples: int, seed: int) -> Any:
    return key_room_diagnostics(env, encode)


#: Ground-truth diagnostics by the kind an env declares as its ``DIAGNOSTICS``; a new kind
#: is a function ``(env, encode, num_samples, seed)`` added here.
GROUND_TRUTH_DIAGNOSTICS: dict[str, Callable[..., Any]] = {
    "rearrangement": _rearrangement,
    "key_room": _key_room,
}


def ground_truth_diagnostics(
    env: Any, encode: Encoder, *, num_samples: int = 2048, seed: int = 0
) -> Any:
    """The ground-truth diagnostics of the kind ``env`` declares (``env.DIAGNOSTICS``).

    Raises:
        ValueError: an env that declares none, or a kind not in
            :data:`GROUND_TRUTH_DIAGNOSTICS`.
    """
    kind = getattr(env, "DIAGNOSTICS", None)
    if kind not in GROUND_TRUTH_DIAGNOSTICS:
        raise ValueError(
            f"{type(env).__name__} declares no ground-truth diagnostics (DIAGNOSTICS is "
            f"{kind!r}, known: {sorted(GROUND_TRUTH_DIAGNOSTICS)}); the label-free "
            "dorp_rl.eval.play_code_dynamics needs none."
        )
    return GROUND_TRUTH_DIAGNOSTICS[kind](env, encode, num_samples, seed)


def object_diagnostics(
    codes: torch.Tensor,
    next_codes: torch.Tensor,
    positions: torch.Tensor,
    next_positions: torch.Tensor,
) -> dict[str, Any]:
    """How codes follow objects, from transitions labelled with each object's position.

    The ground-truth diagnostics of any env whose profile maps its state to object
    positions (:attr:`~dorp_rl.envs.EnvProfile.objects`).

    Args:
        codes, next_codes: int ``[N, C]`` codes of the transitions' frames and next frames.
        positions, next_positions: int ``[N, K]`` a position id per object (any ints:
            equal ids are the same place) in those frames.

    Returns:
        ``change_matrix`` (``[K, C]``: moves of object k alone that changed one-hot c),
        ``assignment`` (object -> one-hot, :func:`best_assignment` of it),
        ``onehot_object``, ``selectivity`` (of the one-hot changes on single-object moves,
        the share on the moved object's one-hot), ``purity`` per one-hot (majority-code
        accuracy over frames grouped by its object's position; ``nan`` unassigned),
        ``min_purity``, and per object ``positions_seen`` and ``moves_per_object`` (its
        moves alone).

    Examples:
        >>> import torch
        >>> from dorp_rl.metrics.diagnostics import object_diagnostics
        >>> pos = torch.tensor([[0, 5], [1, 5], [1, 6], [2, 6]])
        >>> nxt = torch.tensor([[1, 5], [1, 6], [2, 6], [2, 7]])
        >>> out = object_diagnostics(pos.flip(-1), nxt.flip(-1), pos, nxt)
        >>> out["assignment"], out["selectivity"], out["min_purity"]
        ([1, 0], 1.0, 1.0)
    """
    codes, next_codes = codes.long(), next_codes.long()
    positions, next_positions = positions.long(), next_positions.long()
    if codes.shape != next_codes.shape or positions.shape != next_positions.shape:
        raise ValueError(
            "codes / next_codes and positions / next_positions must match in shape, got "
            f"{list(codes.shape)}, {list(next_codes.shape)}, {list(positions.shape)}, "
            f"{list(next_positions.shape)}."
        )
    if codes.dim() != 2 or positions.dim() != 2 or codes.shape[0] != positions.shape[0]:
        raise ValueError(
            f"codes must be [N, C] and positions [N, K] with the same N, got "
            f"{list(codes.shape)} and {list(positions.shape)}."
        )
    k, c = positions.shape[1], codes.shape[1]
    moved = positions != next_positions  # [N, K]
    alone = moved.sum(-1) == 1
    changed = (codes != next_codes)[alone]  # [M, C]
    mover = moved[alone].long().argmax(-1)  # [M]
    change_matrix = torch.zeros((k, c), dtype=torch.int64)
    change_matrix.index_add_(0, mover, changed.long())
    assignment = best_assignment(change_matrix)
    onehot_object: list[int | None] = [None] * c
    for obj, onehot in enumerate(assignment):
        if onehot is not None:
            onehot_object[onehot] = obj
    total = int(change_matrix.sum())
    matched = sum(int(change_matrix[o, h]) for o, h in enumerate(assignment) if h is not None)
    purity: list[float] = []
    for onehot, obj in enumerate(onehot_object):
        if obj is None:
            purity.append(math.nan)
            continue
        _, groups = torch.unique(positions[:, obj], return_inverse=True)
        _, accuracy = _majority_codes(groups, codes[:, onehot], int(groups.max()) + 1)
        purity.append(accuracy)
    assigned = [p for p, o in zip(purity, onehot_object, strict=True) if o is not None]
    return {
        "num_transitions": int(codes.shape[0]),
        "change_matrix": change_matrix.tolist(),
        "assignment": assignment,
        "onehot_object": onehot_object,
        "selectivity": matched / total if total else math.nan,
        "purity": purity,
        "min_purity": min(assigned, default=math.nan),
        "positions_seen": [int(torch.unique(positions[:, o]).numel()) for o in range(k)],
        "moves_per_object": torch.bincount(mover, minlength=k).tolist(),
    }


def play_object_diagnostics(
    buffer: Any,
    encoder: Any,
    objects: Callable[[torch.Tensor], torch.Tensor],
    *,
    chunk_size: int = 1024,
    transitions: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> dict[str, Any]:
    """:func:`object_diagnostics` of an encoder on play transitions (a buffer or a
    TensorDict of them holding ``state`` and ``("next", "state")``), with ``objects``
    mapping a state ``[N, ...]`` to position ids ``[N, K]`` (a profile's
    :attr:`~dorp_rl.envs.EnvProfile.objects`). ``transitions``: the codes of
    :func:`~dorp_rl.planners.encode_transitions` on the same data, if already computed."""
    from tensordict import TensorDictBase

    from dorp_rl.planners.code_graph import encode_transitions

    if transitions is None:
        transitions = encode_transitions(buffer, encoder, chunk_size=chunk_size)
    codes, next_codes = transitions
    storage = getattr(buffer, "storage", None)
    inner = getattr(storage, "_storage", None)
    if storage is None:  # a TensorDict of transitions
        data = buffer
    elif isinstance(inner, TensorDictBase):  # the state columns only, not the frames
        data = inner[: len(storage)]
    else:
        data = storage[: len(storage)]
    for key in ("state", ("next", "state")):
        if key not in data.keys(True):
            raise ValueError(
                f"object diagnostics need the play data's {key!r} (the true state of each "
                "frame), which it does not hold."
            )
    positions = objects(data.get("state"))
    next_positions = objects(data.get(("next", "state")))
    return object_diagnostics(codes, next_codes, positions, next_positions)
