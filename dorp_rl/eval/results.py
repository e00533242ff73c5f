"""Result rows of :func:`~dorp_rl.eval.evaluate_policy` and the tables they go into.

:func:`result_row` turns one evaluation into a flat row with :data:`RESULT_COLUMNS`;
:func:`write_results` writes rows as ``results.csv`` and a markdown ``results.md``.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

#: the columns of a result table, in order
RESULT_COLUMNS: tuple[str, ...] = (
    "setting",
    "method",
    "low_level",
    "tasks",
    "success_rate",
    "mean_steps",
    "mean_lower_bound",
    "steps_over_bound",
    "seconds_per_task",
)


def steps_over_bound(result: dict[str, Any], tasks: TensorDictBase) -> float:
    """Mean over the solved tasks of steps taken / the task's lower bound (``nan`` if none)."""
    solved = torch.tensor(result["success"], dtype=torch.bool)
    if not bool(solved.any()):
        return math.nan
    steps = torch.tensor(result["steps"], dtype=torch.float32)
    bound = tasks["lower_bound"].float()
    return float((steps[solved] / bound[solved]).mean())


def result_row(
    result: dict[str, Any], tasks: TensorDictBase, *, setting: str, method: str, low_level: str
) -> dict[str, Any]:
    """One row of :data:`RESULT_COLUMNS` from an :func:`~dorp_rl.eval.evaluate_policy` result."""
    n = result["num_tasks"]
    return {
        "setting": setting,
        "method": method,
        "low_level": low_level,
        "tasks": n,
        "success_rate": result["success_rate"],
        "mean_steps": result["mean_steps"],
        "mean_lower_bound": result["mean_lower_bound"],
        "steps_over_bound": steps_over_bound(result, tasks),
        "seconds_per_task": result["seconds"] / n,
    }


def _show(value: Any) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.2f}"
    return str(value)


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """``rows`` as a markdown table with :data:`RESULT_COLUMNS` (floats with 2 decimals).

    Examples:
        >>> from dorp_rl.eval import format_table
        >>> row = dict(setting="1obj", method="random", low_level="gt", tasks=4,
        ...            success_rate=0.25, mean_steps=14.0, mean_lower_bound=2.0,
        ...            steps_over_bound=7.0, seconds_per_task=0.01)
        >>> print(format_table([row]).splitlines()[-1])
        | 1obj | random | gt | 4 | 0.25 | 14.00 | 2.00 | 7.00 | 0.01 |
    """
    lines = [
        "| " + " | ".join(RESULT_COLUMNS) + " |",
        "|" + "---|" * len(RESULT_COLUMNS),
    ]
    lines += ["| " + " | ".join(_show(r[c]) for c in RESULT_COLUMNS) + " |" for r in rows]
    return "\n".join(lines)


def write_results(
    rows: Sequence[dict[str, Any]], directory: str | Path, figures: Sequence[str | Path] = ()
) -> tuple[Path, Path]:
    """Writes ``results.csv`` and ``results.md`` (see :data:`RESULT_COLUMNS`) into ``directory``.

    ``figures`` (pictures in ``directory``) are shown in ``results.md`` below the table.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = directory / "results.csv", directory / "results.md"
    with csv_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=RESULT_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    md_path.write_text(
        "# Results\n\nSuccess rate, mean steps of the solved tasks next to their mean lower "
        "bound (sum of Manhattan distances), and mean of steps / bound over them.\n\n"
        + format_table(rows)
        + "\n"
        + "".join(f"\n![{Path(f).stem}]({Path(f).name})\n" for f in figures)
    )
    return csv_path, md_path
