"""Code-quality diagnostics of discrete object codes, measured against ground-truth states.

DORP's planner is only as good as its codes: one one-hot per object, each changing only
when its own object moves, and each code covering a compact, connected patch of that
object's positions. The measures here need only labels, not an env: any encoder is a
plain callable::

    encode(pixels: uint8 [N, C, H, W]) -> int64 [N, K]   # one code index per one-hot

(the encoder's ``argmax`` codes), called in chunks under :func:`torch.no_grad`.

Why not just the paper's Figure 4(c) number (the fraction of single-object moves that
change at most one one-hot)? Each one-hot changes on only 15-25% of moves, so an
untrained or fully entangled encoder already scores ~0.97 on it. The numbers that
separate good codes from bad ones are:

- **selectivity**: of all one-hot changes caused by moving one object, the share that land
  on that object's own one-hot, under the best object-to-one-hot assignment
  (:func:`best_assignment`; chance is about ``1 / K``);
- **purity**: how well the assigned object's own position predicts a one-hot's code
  (majority-code accuracy over states grouped by that position, :func:`majority_codes`);
- **temporal consistency**: the share of codes whose positions form one 4-connected
  region (:func:`connected_fraction`), and the mean number of steps between two states
  that share a code (:func:`mean_steps_within_code`).

:func:`object_diagnostics` computes the first two from transitions labelled with each
object's position (an env profile's ``objects``), :func:`play_object_diagnostics` on play
data. An env's own diagnostics over its true states (the paper's figures for its envs)
come through its profile (:attr:`~dorp_rl.envs.EnvProfile.diagnostics`) and use the
measures here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from dorp_rl.frames import check_frames
from dorp_rl.validation import check_int

#: ``encode(pixels uint8 [N, C, H, W]) -> int64 [N, K]``: one code index per one-hot.
Encoder = Callable[[torch.Tensor], torch.Tensor]

DEFAULT_CHUNK_SIZE = 4096
#: The exact assignment search keeps one entry per subset of the larger side.
_MAX_ASSIGNMENT_SIDE = 20

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "Encoder",
    "best_assignment",
    "connected_fraction",
    "encode_pixels",
    "encode_states",
    "fraction_true",
    "majority_codes",
    "mean_steps_random_pair",
    "mean_steps_within_code",
    "object_diagnostics",
    "play_object_diagnostics",
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
        encode: ``encode(uint8 [n, C, H, W]) -> int64 [n, K]``.
        pixels: uint8 ``[N, C, H, W]``.
        chunk_size: frames per call of ``encode``.

    Returns:
        int64 ``[N, C]`` on the CPU.

    Raises:
        ValueError: if ``pixels`` is not uint8 ``[N, C, H, W]``, or ``encode`` returns
            anything but an int64 ``[n, C]`` tensor of non-negative code indices with the
            same ``C`` for every chunk.
    """
    pixels = check_frames(pixels, "pixels", lead="N")
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


def encode_states(
    env: Any,
    encode: Encoder,
    states: torch.Tensor,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Renders ``[N, *state_shape]`` states with ``env.render_state`` in chunks and encodes
    them (:func:`encode_pixels`): int64 ``[N, K]``."""
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


def majority_codes(
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


def mean_steps_within_code(
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


def mean_steps_random_pair(positions: torch.Tensor, generator: torch.Generator) -> float:
    """Baseline for :func:`mean_steps_within_code`: Manhattan distance of random pairs."""
    partner = torch.randperm(len(positions), generator=generator)
    return float((positions - positions[partner]).abs().sum(-1).double().mean())


def fraction_true(mask: torch.Tensor) -> float:
    """Share of ``True`` in a bool tensor (``nan`` when it is empty)."""
    return float(mask.double().mean()) if mask.numel() else math.nan


# ---------------------------------------------------------------------- #
# From labelled transitions
# ---------------------------------------------------------------------- #
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
        _, accuracy = majority_codes(groups, codes[:, onehot], int(groups.max()) + 1)
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

    from dorp_rl.planners.play_codes import encode_transitions

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
