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
from matplotlib.patches import Patch
from torchrl.envs import EnvBase

from dorp_rl.envs import EnvProfile, profile_of
from dorp_rl.metrics.diagnostics import Encoder

__all__ = [
    "WALL_COLOUR",
    "as_code_array",
    "code_colours",
    "draw_code_map",
    "plot_code_maps",
    "plot_factorization_histogram",
    "save_figure",
    "write_diagnostic_plots",
]

_PALETTE = np.concatenate(
    [np.asarray(matplotlib.colormaps[name].colors)[:, :3] for name in ("tab20", "tab20b", "tab20c")]
)  # [60, 3] floats in [0, 1]
_NO_CODE = np.array([1.0, 1.0, 1.0])  # cells without a code (unseen, invalid in that condition)
#: colour of walls in code maps
WALL_COLOUR = np.array([0.0, 0.0, 0.0])
_MAX_ANNOTATED_CELLS = 256


def as_code_array(codes: Any) -> np.ndarray:
    """Codes as an int64 numpy array (tensors are moved to the CPU)."""
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
    codes = as_code_array(codes)
    rgb = _PALETTE[np.maximum(codes, 0) % len(_PALETTE)]
    rgb[codes < 0] = _NO_CODE
    return rgb


def draw_code_map(ax, codes: np.ndarray, rgb: np.ndarray, title: str, annotate: bool) -> None:
    """One code-map panel on ``ax`` (a matplotlib axes): cells as squares, rows downwards
    as in the frames, each code index written in its cell when ``annotate`` and the map is
    small."""
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


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Writes ``fig`` as a PNG at ``path`` (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def plot_code_maps(
    result_or_codes: Mapping[str, Any]
    | torch.Tensor
    | np.ndarray
    | Sequence[torch.Tensor | np.ndarray | None],
    path: str | Path,
    *,
    title: str | None = None,
    annotate: bool = True,
    axes: tuple[str, str] = ("row", "column"),
) -> Path:
    """Code maps of one-hots over an object's positions, like the paper's Figure 5.

    Args:
        result_or_codes: one of

            - a dict with ``code_maps`` (per one-hot a map or ``None``) and optionally
              ``onehot_object`` (per one-hot its object), as an env's diagnostics give
              (e.g. :func:`~dorp_rl.envs.rearrangement_diagnostics`: one panel per
              assigned one-hot, majority code over its object's positions);
            - an int ``[rows, cols]`` map (one panel), or ``[C, rows, cols]`` (one panel
              per one-hot);
            - a list of per-one-hot maps (``None`` entries are skipped).

            ``-1`` marks positions without a code (drawn white).
        path: PNG file to write (parent directories are created).
        title: figure title.
        annotate: write each cell's code index (small maps only).
        axes: the labels of the rows and the columns.

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
            maps.append(as_code_array(code_map))
            obj = objects[c] if c < len(objects) else None
            labels.append(f"one-hot {c}" + ("" if obj is None else f" (object {obj})"))
    elif isinstance(result_or_codes, torch.Tensor | np.ndarray):
        array = as_code_array(result_or_codes)
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
                maps.append(as_code_array(code_map))
                labels.append(f"one-hot {c}")
    if not maps:
        raise ValueError("no code map to draw (every one-hot is unassigned).")
    fig = Figure(figsize=(2.8 * len(maps), 3.4))
    for i, (code_map, label) in enumerate(zip(maps, labels, strict=True)):
        ax = fig.add_subplot(1, len(maps), i + 1)
        used = len(np.unique(code_map[code_map >= 0]))
        draw_code_map(ax, code_map, code_colours(code_map), f"{label}: {used} codes", annotate)
        ax.set_xlabel(axes[1], fontsize=8)
        if i == 0:
            ax.set_ylabel(axes[0], fontsize=8)
    fig.suptitle(title or "codes over positions", fontsize=10)
    return save_figure(fig, path)


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
            :func:`~dorp_rl.envs.rearrangement_diagnostics` /
            :func:`~dorp_rl.envs.key_room_diagnostics` (counts, totals,
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
    return save_figure(fig, path)


def write_diagnostic_plots(
    env: EnvBase,
    encode: Encoder,
    out_dir: str | Path,
    *,
    num_samples: int = 4096,
    seed: int = 0,
    result: Mapping[str, Any] | None = None,
    profile: EnvProfile | None = None,
) -> dict[str, Path]:
    """Writes the pictures of ``env``'s own code diagnostics into ``out_dir``.

    The diagnostics are those of the env's profile
    (:attr:`~dorp_rl.envs.EnvProfile.diagnostics`; the paper's envs: code maps and the
    factorisation histogram).

    Args:
        env: the environment.
        encode: ``encode(uint8 [n, C, H, W]) -> int64 [n, K]``.
        out_dir: directory (created if needed).
        num_samples, seed: for diagnostics that sample states.
        result: the diagnostics' dict for this env and encoder, if already computed.
        profile: the env's profile (default: the registered profile of its class).

    Returns:
        Picture name -> path of the written PNG.

    Raises:
        ValueError: the env's profile declares no diagnostics or no pictures.
    """
    profile = profile_of(env) if profile is None else profile
    diagnostics = None if profile is None else profile.diagnostics
    if diagnostics is None or diagnostics.pictures is None:
        raise ValueError(
            f"{type(env).__name__}'s profile declares no code diagnostics with pictures "
            "(EnvProfile.diagnostics): code maps need the true state of each frame."
        )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if result is None:
        result = diagnostics.measure(env, encode, num_samples, seed)
    return diagnostics.pictures(env, encode, out_dir, result)
