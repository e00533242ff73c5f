"""How the tasks of an evaluation ended: failure summaries and task tables.

Every evaluation (:func:`~dorp_rl.eval.evaluate_policy`,
:func:`~dorp_rl.eval.evaluate_parallel`) returns one record per task (``records``):
``task``, ``outcome`` (``"solved"``, ``"step_limit"``, or the reason the policy gave the
task up: the DORP policy's ``"no_path"``, ``"goal_stalled"``, ``"removal_limit"``),
``steps``, and what the policy adds (the DORP policy: the group left without a path,
the phase it ended in, edge removals, re-entries, waypoint plans, waypoints reached and
the steps spent per phase). :func:`summarize_failures` counts them,
:func:`format_failures` says it in two lines and :func:`failure_section` for every
row of a results table, :func:`tasks_to_draw` picks the tasks to
draw (failures first) and :func:`write_task_records` writes them as ``tasks.csv``.
"""

from __future__ import annotations

import csv
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dorp_rl.eval.tasks import SOLVED

#: the per-task counts whose means :func:`summarize_failures` reports (those present)
COUNTS: tuple[str, ...] = (
    "edge_removals",
    "reentries",
    "plans",
    "waypoints",
    "waypoint_steps",
    "goal_steps",
)
#: leading columns of ``tasks.csv`` (any other record field follows them)
TASK_COLUMNS: tuple[str, ...] = (
    "setting",
    "method",
    "low_level",
    "seed",
    "task",
    "outcome",
    "group",
    "phase",
    "steps",
    "lower_bound",
    *COUNTS,
    "relaxed",
)


def _check_records(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    records = list(records)
    for i, record in enumerate(records):
        if not isinstance(record, dict) or "outcome" not in record:
            raise ValueError(
                f"record {i} must be a dict with an 'outcome' (an evaluation's 'records'), "
                f"got {record!r:.80}."
            )
    return records


def summarize_failures(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Counts of how tasks ended, and the mean counts of solved and failed tasks.

    Returns:
        ``tasks``, ``solved``, ``failed`` (indices of the unsolved tasks), ``outcomes``
        (count per outcome of the unsolved tasks, most frequent first), ``groups``
        (per outcome, the count per group where records name one), and ``means``:
        ``{"solved": {count: mean}, "failed": {...}}`` over :data:`COUNTS` present.

    Examples:
        >>> from dorp_rl.eval.failures import summarize_failures
        >>> records = [dict(task=0, outcome="solved", steps=9, edge_removals=0),
        ...            dict(task=1, outcome="no_path", group=1, steps=40, edge_removals=6),
        ...            dict(task=2, outcome="step_limit", steps=40, edge_removals=2)]
        >>> s = summarize_failures(records)
        >>> s["failed"], s["outcomes"], s["groups"]
        ([1, 2], {'no_path': 1, 'step_limit': 1}, {'no_path': {1: 1}})
        >>> s["means"]["failed"]["edge_removals"]
        4.0
    """
    records = _check_records(records)
    failed = [r for r in records if r["outcome"] != SOLVED]
    outcomes = Counter(r["outcome"] for r in failed)
    groups: dict[str, dict[int, int]] = {}
    for r in failed:
        if r.get("group") is not None:
            by_group = groups.setdefault(r["outcome"], {})
            by_group[r["group"]] = by_group.get(r["group"], 0) + 1
    means: dict[str, dict[str, float]] = {}
    for name, part in (
        ("solved", [r for r in records if r["outcome"] == SOLVED]),
        ("failed", failed),
    ):
        means[name] = {
            key: sum(float(r[key]) for r in part) / len(part)
            for key in COUNTS
            if part and all(key in r for r in part)
        }
    return {
        "tasks": len(records),
        "solved": len(records) - len(failed),
        "failed": [int(r["task"]) for r in failed],
        "outcomes": dict(outcomes.most_common()),
        "groups": {k: dict(sorted(v.items())) for k, v in groups.items()},
        "means": means,
    }


def format_failures(records: Sequence[dict[str, Any]], name: str = "") -> str:
    """Two lines on how the tasks ended (what failed, how, and where the steps went).

    Examples:
        >>> from dorp_rl.eval.failures import format_failures
        >>> records = [dict(task=0, outcome="solved", steps=9),
        ...            dict(task=1, outcome="no_path", group=1, steps=40)]
        >>> print(format_failures(records, "dorp"))
        dorp: 1 of 2 solved; 1 failed: no_path 1 (group 1: 1); failed tasks: 1
    """
    s = summarize_failures(records)
    head = f"{name}: " if name else ""
    text = f"{head}{s['solved']} of {s['tasks']} solved"
    if s["failed"]:
        parts = []
        for outcome, count in s["outcomes"].items():
            by_group = s["groups"].get(outcome)
            where = (
                " (" + ", ".join(f"group {g}: {n}" for g, n in by_group.items()) + ")"
                if by_group
                else ""
            )
            parts.append(f"{outcome} {count}{where}")
        shown = s["failed"][:12]
        more = f" and {len(s['failed']) - len(shown)} more" if len(s["failed"]) > len(shown) else ""
        text += (
            f"; {len(s['failed'])} failed: {', '.join(parts)}; failed tasks: "
            f"{', '.join(map(str, shown))}{more}"
        )
    counts = [k for k in COUNTS if k in s["means"].get("solved", {}) or k in s["means"]["failed"]]
    if counts:
        cells = []
        for key in counts:
            solved = s["means"]["solved"].get(key)
            lost = s["means"]["failed"].get(key)
            shown_values = " / ".join("-" if v is None else f"{v:.1f}" for v in (solved, lost))
            cells.append(f"{key.replace('_', ' ')} {shown_values}")
        text += "\n" + " " * len(head) + "per task (solved / failed): " + ", ".join(cells)
    return text


def tasks_to_draw(records: Sequence[dict[str, Any]], count: int) -> list[int]:
    """``count`` task indices to draw: the failed tasks first (in task order), then the
    solved ones.

    Examples:
        >>> from dorp_rl.eval.failures import tasks_to_draw
        >>> records = [dict(task=i, outcome="solved" if i != 3 else "no_path") for i in range(5)]
        >>> tasks_to_draw(records, 2)
        [3, 0]
    """
    records = _check_records(records)
    failed = [int(r["task"]) for r in records if r["outcome"] != SOLVED]
    solved = [int(r["task"]) for r in records if r["outcome"] == SOLVED]
    return (failed + solved)[: max(0, int(count))]


def write_task_records(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """Writes the task records of result rows (``row["per_task"]["records"]``, with the
    row's setting, method, low level and seed) as one CSV, :data:`TASK_COLUMNS` first.
    The low level tells apart the rows of one method planned through different models."""
    path = Path(path)
    lines: list[dict[str, Any]] = []
    for row in rows:
        per_task = row.get("per_task") or {}
        bounds = per_task.get("lower_bound") or []
        for record in per_task.get("records") or []:
            task = int(record["task"])
            line = {
                "setting": row.get("setting", ""),
                "method": row.get("method", ""),
                "low_level": row.get("low_level", ""),
                "seed": row.get("seed", ""),
                **record,
            }
            if "lower_bound" not in line and task < len(bounds):
                line["lower_bound"] = bounds[task]
            lines.append(line)
    extra = sorted({k for line in lines for k in line} - set(TASK_COLUMNS))
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[*TASK_COLUMNS, *extra], restval="")
        writer.writeheader()
        writer.writerows(lines)
    return path


def failure_section(rows: Sequence[dict[str, Any]], *, by_seed: bool = False) -> str:
    """The markdown section of a ``results.md`` on how each row's tasks ended (from the
    task records of the rows; :func:`write_task_records` writes one line per task).
    ``by_seed``: name each row's seed (the rows of a seed sweep). A method with rows
    through several low levels names the low level of each."""
    lines = []
    levels: dict[tuple, set] = {}
    for row in rows:
        levels.setdefault((row["setting"], row["method"]), set()).add(row.get("low_level"))
    for row in rows:
        records = (row.get("per_task") or {}).get("records")
        if records:
            label = f"{row['setting']} {row['method']}"
            if len(levels[(row["setting"], row["method"])]) > 1:
                label += f" ({row.get('low_level')})"
            lines.append(
                format_failures(records, label + (f" seed {row['seed']}" if by_seed else ""))
            )
    body = "\n".join("    " + line for text in lines for line in text.splitlines())
    return (
        "## How the tasks ended\n\nPer method: tasks solved, the failures by how they ended "
        "(step_limit; given up with no_path, for which group; goal_stalled; "
        "removal_limit), and mean counts per task. One line per task: "
        "[tasks.csv](tasks.csv).\n\n" + (body or "    (no task records)")
    )
