"""Pictures of learned codes: code maps (the paper's Figures 5 and 6) and the
factorisation histogram (Figure 4(c)).

Everything draws on a bare :class:`matplotlib.figure.Figure` with the Agg canvas: no
pyplot, no display, no change to matplotlib's global backend. A code keeps the same
colour in every panel (colour = code index modulo a 60-colour qualitative palette) and,
where the map is small enough, its index is written in the cell.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle

from dorp_rl.envs.key_rooms import KeyRoomEnv
from dorp_rl.envs.rearrangement import ObjectRearrangementEnv
from dorp_rl.metrics.diagnostics import (
    DEFAULT_CHUNK_SIZE,
    Encoder,
    key_room_diagnostics,
    rearrangement_code_maps,
    rearrangement_diagnostics,
)

__all__ = [
    "code_colours",
    "plot_factorization_histogram",
    "plot_key_room_code_map",
    "plot_rearrangement_code_map",
    "write_diagnostic_plots",
]

_PALETTE = np.concatenate(
    [np.asarray(matplotlib.colormaps[name].colors)[:, :3] for name in ("tab20", "tab20b", "tab20c")]
)  # [60, 3] floats in [0, 1]
_NO_CODE = np.array([1.0, 1.0, 1.0])  # cells without a code (unseen, invalid in that condition)
_WALL = np.array([0.0, 0.0, 0.0])
_MAX_ANNOTATED_CELLS = 256


def _as_array(codes: Any) -> np.ndarray:
    if isinstance(codes, torch.Tensor):
        codes = codes.detach().cpu().numpy()
    return np.asarray(codes, dtype=np.int64)


def code_colours(codes: torch.Tensor | np.ndarray) -> np.ndarray:
    """RGB image of a code map: float ``[H, W, 3]`` in ``[0, 1]`` (white where ``-1``).

    Args:
        codes: int ``[H, W]`` codes, ``-1`` for cells without a code.

    Examples:
        >>> import torch
        >>> from dorp_rl.viz import code_colours
        >>> image = code_colours(torch.tensor([[0, 1], [-1, 1]]))
        >>> image.shape, image[1, 0].tolist(), bool((image[0, 1] == image[1, 1]).all())
        ((2, 2, 3), [1.0, 1.0, 1.0], True)
    """
    codes = _as_array(codes)
    rgb = _PALETTE[np.maximum(codes, 0) % len(_PALETTE)]
    rgb[codes < 0] = _NO_CODE
    return rgb


def _draw_map(ax, codes: np.ndarray, rgb: np.ndarray, title: str, annotate: bool) -> None:
    """One code-map panel on ``ax``: cells as squares, rows downwards as in the frames."""
    rows, cols = codes.shape
    ax.imshow(rgb, interpolation="nearest", extent=(-0.5, cols - 0.5, rows - 0.5, -0.5))
    ax.set_title(title, fontsize=9)
    ax.set_xticks(range(0, cols, 2))
    ax.set_yticks(range(0, rows, 2))
    ax.tick_params(labelsize=7)
    if annotate and codes.size <= _MAX_ANNOTATED_CELLS:
        for r in range(rows):
            for c in range(cols):
                if codes[r, c] >= 0:
                    shade = rgb[r, c] @ np.array([0.299, 0.587, 0.114])
                    ax.text(
                        c,
                        r,
                        str(int(codes[r, c])),
                        ha="center",
                        va="center",
                        fontsize=5,
                        color="black" if shade > 0.5 else "white",
                    )


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def plot_rearrangement_code_map(
    result_or_codes: Mapping[str, Any]
    | torch.Tensor
    | np.ndarray
    | Sequence[torch.Tensor | np.ndarray | None],
    path: str | Path,
    *,
    title: str | None = None,
    annotate: bool = True,
) -> Path:
    """Code maps over block top-left positions, like the paper's Figure 5.

    Args:
        result_or_codes: one of

            - the dict of :func:`~dorp_rl.metrics.diagnostics.rearrangement_diagnostics`
              (its ``code_maps``: one panel per assigned one-hot, majority code over
              its object's positions);
            - an int ``[rows, cols]`` map (one panel; 15 x 13 for 2x4 blocks), or
              ``[C, rows, cols]`` (one panel per one-hot);
            - a list of per-one-hot maps (``None`` entries are skipped), as returned
              by :func:`~dorp_rl.metrics.diagnostics.rearrangement_code_maps`.

            ``-1`` marks positions without a code (drawn white).
        path: PNG file to write (parent directories are created).
        title: figure title.
        annotate: write each cell's code index (small maps only).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    labels: list[str] = []
    maps: list[np.ndarray] = []
    if isinstance(result_or_codes, Mapping):
        objects = result_or_codes.get("onehot_object") or []
        for c, code_map in enumerate(result_or_codes["code_maps"]):
            if code_map is None:
                continue
            maps.append(_as_array(code_map))
            obj = objects[c] if c < len(objects) else None
            labels.append(f"one-hot {c}" + ("" if obj is None else f" (object {obj})"))
    elif isinstance(result_or_codes, torch.Tensor | np.ndarray):
        array = _as_array(result_or_codes)
        if array.ndim == 2:
            array = array[None]
        if array.ndim != 3:
            raise ValueError(
                f"codes must be [rows, cols] or [C, rows, cols], got shape {list(array.shape)}."
            )
        maps = list(array)
        labels = [f"one-hot {c}" for c in range(len(maps))]
    else:
        for c, code_map in enumerate(result_or_codes):
            if code_map is not None:
                maps.append(_as_array(code_map))
                labels.append(f"one-hot {c}")
    if not maps:
        raise ValueError("no code map to draw (every one-hot is unassigned).")
    fig = Figure(figsize=(2.8 * len(maps), 3.4))
    for i, (code_map, label) in enumerate(zip(maps, labels, strict=True)):
        ax = fig.add_subplot(1, len(maps), i + 1)
        used = len(np.unique(code_map[code_map >= 0]))
        _draw_map(ax, code_map, code_colours(code_map), f"{label}: {used} codes", annotate)
        ax.set_xlabel("block column", fontsize=8)
        if i == 0:
            ax.set_ylabel("block row", fontsize=8)
    fig.suptitle(title or "codes over block positions", fontsize=10)
    return _save(fig, path)


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
    wall = env.wall.cpu().numpy()
    key_cell = env.key.cpu().numpy().nonzero()
    door_cells = np.argwhere(env.door.cpu().numpy())
    fig = Figure(figsize=(7.6, 4.0))
    for i, (codes, name) in enumerate(
        ((codes_without_key, "without key"), (codes_with_key, "with key"))
    ):
        codes = _as_array(codes)
        if codes.shape != wall.shape:
            raise ValueError(f"code maps must be {list(wall.shape)}, got {list(codes.shape)}.")
        rgb = code_colours(codes)
        rgb[wall] = _WALL
        ax = fig.add_subplot(1, 2, i + 1)
        used = len(np.unique(codes[codes >= 0]))
        _draw_map(ax, codes, rgb, f"agent codes {name}: {used} codes", annotate)
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
    return _save(fig, path)


def plot_factorization_histogram(
    change_matrix: Mapping[str, Any] | torch.Tensor | np.ndarray | Sequence[Sequence[int]],
    path: str | Path,
    *,
    totals: Sequence[int] | None = None,
    row_labels: Sequence[str] | None = None,
    assignment: Sequence[int | None] | None = None,
    title: str | None = None,
) -> Path:
    """Which one-hots change when one thing moves (the paper's Figure 4(c)).

    One group of bars per row (moved object, or event type), one bar per one-hot: the
    share of that row's moves that changed the one-hot (or, without ``totals``, the
    share of that row's one-hot changes). Bars of the assigned one-hot are hatched.

    Args:
        change_matrix: int ``[R, C]`` counts, or the dict of
            :func:`~dorp_rl.metrics.diagnostics.rearrangement_diagnostics` /
            :func:`~dorp_rl.metrics.diagnostics.key_room_diagnostics` (counts, totals,
            labels and assignment are then taken from it).
        path: PNG file to write.
        totals: ``[R]`` moves per row, to turn counts into rates.
        row_labels: ``[R]`` group names (default ``object r``).
        assignment: per row its own one-hot (``None`` for none), for the hatching.
        title: figure title.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.
    """
    if isinstance(change_matrix, Mapping):
        result = change_matrix
        change_matrix = result["change_matrix"]
        if "moves_per_object" in result:
            totals = totals if totals is not None else result["moves_per_object"]
            assignment = assignment if assignment is not None else result["assignment"]
        else:  # key rooms: rows are key events and agent moves
            totals = totals if totals is not None else result["change_totals"]
            row_labels = row_labels or ["key events", "agent moves"]
            assignment = assignment or [result["key_onehot"], result["agent_onehot"]]
    counts = np.asarray(
        change_matrix.detach().cpu().numpy()
        if isinstance(change_matrix, torch.Tensor)
        else change_matrix,
        dtype=np.float64,
    )
    if counts.ndim != 2:
        raise ValueError(f"change_matrix must be [rows, one-hots], got {list(counts.shape)}.")
    num_rows, num_onehots = counts.shape
    if totals is not None:
        heights = counts / np.maximum(np.asarray(totals, dtype=np.float64), 1)[:, None]
        ylabel = "fraction of moves changing the one-hot"
    else:
        heights = counts / np.maximum(counts.sum(1, keepdims=True), 1)
        ylabel = "share of one-hot changes"
    labels = (
        list(row_labels) if row_labels is not None else [f"object {r}" for r in range(num_rows)]
    )
    fig = Figure(figsize=(max(4.0, 1.2 * num_rows * max(1, num_onehots) ** 0.5 + 2), 3.4))
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / num_onehots
    x = np.arange(num_rows)
    for c in range(num_onehots):
        hatch = [
            "//" if assignment is not None and r < len(assignment) and assignment[r] == c else ""
            for r in range(num_rows)
        ]
        bars = ax.bar(
            x - 0.4 + (c + 0.5) * width,
            heights[:, c],
            width,
            color=_PALETTE[(2 * c) % len(_PALETTE)],
            edgecolor="black",
            linewidth=0.5,
        )
        for bar, h in zip(bars, hatch, strict=True):
            bar.set_hatch(h)
    handles = [
        Patch(facecolor=_PALETTE[(2 * c) % len(_PALETTE)], edgecolor="black", label=f"one-hot {c}")
        for c in range(num_onehots)
    ]
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_ylim(0, max(1e-3, float(heights.max(initial=0.0))) * 1.15)
    ax.legend(handles=handles, fontsize=7, ncol=min(num_onehots, 4))
    ax.set_title(title or "one-hots changed per moved object (hatched: assigned)", fontsize=9)
    return _save(fig, path)


def write_diagnostic_plots(
    env: ObjectRearrangementEnv | KeyRoomEnv,
    encode: Encoder,
    out_dir: str | Path,
    *,
    num_samples: int = 4096,
    seed: int = 0,
    result: Mapping[str, Any] | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> dict[str, Path]:
    """Writes every picture relevant to the environment into ``out_dir``.

    Rearrangement: ``code_map.png`` (exact map for 1 object, majority maps per one-hot
    otherwise) and ``factorization_histogram.png``. Key rooms: ``code_map.png`` (agent
    codes without/with the key) and ``factorization_histogram.png`` (one-hot changes on
    key events and agent moves).

    Args:
        env: a rearrangement or key-room environment.
        encode: ``encode(uint8 [n, 3, 16, 16]) -> int64 [n, C]``.
        out_dir: directory (created if needed).
        num_samples, seed: for rearrangement, as in
            :func:`~dorp_rl.metrics.diagnostics.rearrangement_diagnostics`.
        result: an already computed diagnostics dict for this env and encoder, to
            avoid recomputing it.
        chunk_size: frames per call of ``encode``.

    Returns:
        Picture name -> path of the written PNG.
    """
    kind = getattr(env, "DIAGNOSTICS", None)
    if kind not in ("rearrangement", "key_room"):
        raise ValueError(
            f"{type(env).__name__} declares no ground-truth diagnostics (DIAGNOSTICS is "
            f"{kind!r}; 'rearrangement' and 'key_room' are drawn): code maps need the true "
            "state of each frame."
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if kind == "rearrangement":
        if result is None:
            result = rearrangement_diagnostics(env, encode, num_samples, seed, chunk_size)
        maps: Any = result
        if env.num_objects == 1:
            maps = rearrangement_code_maps(env, encode, chunk_size=chunk_size)
        title = (
            f"{env.num_objects}-object rearrangement: selectivity {result['selectivity']:.2f}, "
            f"min purity {result['min_purity']:.2f}"
        )
        return {
            "code_map": plot_rearrangement_code_map(maps, out_dir / "code_map.png", title=title),
            "factorization_histogram": plot_factorization_histogram(
                result, out_dir / "factorization_histogram.png"
            ),
        }
    if result is None:
        result = key_room_diagnostics(env, encode, chunk_size=chunk_size, with_steps=False)
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
