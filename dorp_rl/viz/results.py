"""Plots of result rows: success next to the paper's, steps against the lower bound.

Rows are those of :func:`~dorp_rl.eval.result_row`; the steps plot needs each row's
``per_task`` entry (``success``, ``steps`` and ``lower_bound`` lists, one per task).
Drawn on a bare :class:`~matplotlib.figure.Figure` with the Agg canvas (no pyplot).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from dorp_rl.eval.results import paper_figures

__all__ = ["plot_results", "plot_steps_vs_bound", "plot_success"]


def _label(row: dict[str, Any]) -> str:
    level = "" if row["low_level"] in ("gt", "none") else f" ({row['low_level']})"
    return f"{row['setting']} {row['method']}{level}"


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def _paper_success(row: dict[str, Any], paper: dict[str, dict[str, float]]) -> float | None:
    value = paper.get(row["setting"], {}).get(row["method"])
    if value is None:  # the ablations of Table 1
        value = paper_figures(row["setting"], row["method"], row.get("low_level", "gt"))[0]
    return value


def plot_success(
    rows: Sequence[dict[str, Any]], path: str | Path, paper: dict[str, dict[str, float]]
) -> Path:
    """Bars of each row's success rate, with the paper's beside it (``paper[setting][method]``,
    else :func:`~dorp_rl.eval.results.paper_figures`)."""
    fig = Figure(figsize=(max(4.0, 1.2 * len(rows) + 1.5), 3.2))
    ax = fig.add_subplot()
    xs = range(len(rows))
    ax.bar([x - 0.2 for x in xs], [r["success_rate"] for r in rows], 0.4, label="this run")
    known = [(x, _paper_success(r, paper)) for x, r in enumerate(rows)]
    known = [(x, v) for x, v in known if v is not None]
    if known:
        ax.bar(
            [x + 0.2 for x, _ in known],
            [v for _, v in known],
            0.4,
            color="lightgrey",
            hatch="//",
            label="paper (VF: with SV2P)",
        )
    ax.set_xticks(list(xs), [_label(r) for r in rows], rotation=20, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate")
    ax.legend(loc="lower right", fontsize="small")
    return _save(fig, Path(path))


def plot_steps_vs_bound(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Steps of every solved task against its lower bound, one colour per row."""
    fig = Figure(figsize=(4.5, 4.0))
    ax = fig.add_subplot()
    top = 1.0
    for row in rows:
        per_task = row.get("per_task") or {}
        solved = [i for i, ok in enumerate(per_task.get("success", [])) if ok]
        bounds = [per_task["lower_bound"][i] for i in solved]
        steps = [per_task["steps"][i] for i in solved]
        if solved:
            ax.scatter(bounds, steps, s=14, alpha=0.7, label=_label(row))
            top = max(top, *bounds, *steps)
    ax.plot([0, top], [0, top], "k--", linewidth=1, label="steps = lower bound")
    ax.set_xlabel("lower bound (sum of Manhattan distances)")
    ax.set_ylabel("steps taken (solved tasks)")
    ax.legend(fontsize="small")
    return _save(fig, Path(path))


def plot_results(
    rows: Sequence[dict[str, Any]], directory: str | Path, paper: dict[str, dict[str, float]]
) -> list[Path]:
    """Writes ``success.png`` and ``steps.png`` for ``rows`` into ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    return [
        plot_success(rows, directory / "success.png", paper),
        plot_steps_vs_bound(rows, directory / "steps.png"),
    ]
