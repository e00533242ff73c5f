"""Result rows of :func:`~dorp_rl.eval.evaluate_policy` and the tables they go into.

:func:`result_row` turns one evaluation into a flat row with :data:`RESULT_COLUMNS`;
:func:`write_results` writes rows as ``results.csv`` and a markdown ``results.md``.
:func:`paper_figures` reads the paper's Table 1 (and its key-room figures,
:data:`dorp_rl.envs.paper.PAPER_TABLE`); :func:`add_paper_figures` puts them beside a row
(:data:`PAPER_COLUMNS`) and :func:`format_paper_table` lays rows out as Table 1. :func:`write_timings` writes the
wall-clock of each stage of a run and :func:`format_time_by_kind` what dominates it.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from dorp_rl.envs.paper import PAPER_TABLE, PAPER_THROUGH_VIDEO_MODEL

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

#: the paper's figures beside ours, in ``dorp reproduce --paper`` tables
PAPER_COLUMNS: tuple[str, ...] = ("paper_success_rate", "paper_steps")

#: the paper's names of the methods (rows of Table 1)
PAPER_METHOD_NAMES: dict[str, str] = {
    "dorp": "DORP",
    "dorp-arbitrary": "– arbitrary weight",
    "dorp-identity": "– identity weight",
    "dorp-full": "– full graph",
    "vf-rs": "VF-RS",
    "vf-cem": "VF-CEM",
    "random": "random",
}


def paper_figures(setting: str, method: str, low_level: str = "gt") -> tuple[float | None, str]:
    """The paper's (success rate, steps) for ``method`` in ``setting`` (``(None, "")``:
    not reported). ``3obj-full``/``5obj-full`` with ``dorp`` are the full-graph rows;
    through a learned model (``low_level`` not ``gt``/``none``), the paper's figures
    through its video model where they differ (key-wall: 9 of 10 with SV2P).

    Examples:
        >>> from dorp_rl.eval.results import paper_figures
        >>> paper_figures("3obj", "dorp-identity"), paper_figures("5obj", "vf-cem")
        ((0.48, '83 ± 23'), (0.1, 'max'))
        >>> paper_figures("3obj-full", "dorp"), paper_figures("5obj", "dorp-identity")
        ((1.0, '76 ± 26'), (None, ''))
    """
    if setting.endswith("-full") and method == "dorp":
        setting, method = setting.removesuffix("-full"), "dorp-full"
    if low_level not in ("gt", "none") and (setting, method) in PAPER_THROUGH_VIDEO_MODEL:
        return PAPER_THROUGH_VIDEO_MODEL[setting, method]
    return PAPER_TABLE.get((setting, method), (None, ""))


def add_paper_figures(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with :data:`PAPER_COLUMNS` filled in from :func:`paper_figures`."""
    success, steps = paper_figures(row["setting"], row["method"], row.get("low_level", "gt"))
    return {**row, "paper_success_rate": "" if success is None else success, "paper_steps": steps}


def steps_spread(row: dict[str, Any]) -> str:
    """Steps of the solved tasks as ``mean ± std`` (the paper's form) from ``row["per_task"]``;
    ``"max"`` when no task was solved, ``""`` without per-task figures."""
    per_task = row.get("per_task") or {}
    if not per_task:
        return ""
    steps = [s for s, ok in zip(per_task["steps"], per_task["success"], strict=True) if ok]
    if not steps:
        return "max"
    values = torch.tensor(steps, dtype=torch.float64)
    std = float(values.std()) if len(steps) > 1 else 0.0
    return f"{float(values.mean()):.0f} ± {std:.0f}"


def format_paper_table(rows: Sequence[dict[str, Any]]) -> str:
    """Rows laid out as the paper's Table 1: one line per method, per setting our success
    rate and steps with the paper's in brackets (``-``: not run here or not reported).

    Args:
        rows: result rows (with ``per_task`` for the steps' spread; pooled over seeds by
            :func:`pool_seeds`, the success rate shows ``± std`` over the seeds).
    """
    settings = list(dict.fromkeys(r["setting"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    by_key = {(r["setting"], r["method"]): r for r in rows}
    header = "| method | " + " | ".join(f"{s} SR | {s} steps" for s in settings) + " |"
    lines = [header, "|---|" + "---|---|" * len(settings)]
    for method in methods:
        cells = [PAPER_METHOD_NAMES.get(method, method)]
        for setting in settings:
            row = by_key.get((setting, method))
            paper_sr, paper_steps = paper_figures(
                setting, method, (row or {}).get("low_level", "gt")
            )
            paper_sr_text = "-" if paper_sr is None else f"{paper_sr:.2f}"
            if row is None:
                cells += [f"- ({paper_sr_text})", f"- ({paper_steps or '-'})"]
                continue
            spread = row.get("success_rate_std")
            spread_text = f" ± {spread:.2f}" if isinstance(spread, float) else ""
            cells += [
                f"{row['success_rate']:.2f}{spread_text} ({paper_sr_text})",
                f"{steps_spread(row) or _show(row['mean_steps'])} ({paper_steps or '-'})",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


#: columns a seed sweep (``dorp reproduce --paper --seeds``) adds to its results
SEED_COLUMNS: tuple[str, ...] = ("seed", "success_rate_std")


def pool_seeds(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (setting, method, low level) over the seeds of a sweep.

    Rows that share a setting, method and low level (one per seed, each with
    ``per_task``) are pooled task by task: ``success_rate``, ``mean_steps``,
    ``mean_lower_bound`` and ``steps_over_bound`` over every task of every seed,
    ``seconds_per_task`` their mean, ``seed`` ``"all"`` and ``success_rate_std`` the
    standard deviation of the seeds' success rates. A group of one row is kept as it is.

    Examples:
        >>> rows = [dict(setting="1obj", method="dorp", low_level="gt", tasks=2, seed=s,
        ...              seconds_per_task=1.0, per_task=dict(success=ok, steps=[4, 8],
        ...              lower_bound=[2, 4])) for s, ok in ((0, [1, 1]), (1, [1, 0]))]
        >>> pooled = pool_seeds(rows)[0]
        >>> pooled["success_rate"], pooled["mean_steps"], pooled["steps_over_bound"]
        (0.75, 5.333333333333333, 2.0)
        >>> pooled["tasks"], pooled["seed"], round(pooled["success_rate_std"], 3)
        (4, 'all', 0.354)
    """
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["setting"], row["method"], row.get("low_level", "gt")), []).append(
            row
        )
    pooled: list[dict[str, Any]] = []
    for group in groups.values():
        if len(group) == 1:
            pooled.append(group[0])
            continue
        per_task = {
            key: [v for row in group for v in row["per_task"][key]]
            for key in ("success", "steps", "lower_bound")
        }
        if all("records" in row["per_task"] for row in group):
            per_task["records"] = [
                {**record, "seed": row.get("seed")}
                for row in group
                for record in row["per_task"]["records"]
            ]
        solved = [i for i, ok in enumerate(per_task["success"]) if ok]
        steps = [float(per_task["steps"][i]) for i in solved]
        bounds = [float(per_task["lower_bound"][i]) for i in solved]
        rates = torch.tensor([sum(r["per_task"]["success"]) / len(r["per_task"]["success"])
                              for r in group], dtype=torch.float64)  # fmt: skip
        pooled.append(
            {
                **group[0],
                "tasks": len(per_task["success"]),
                "success_rate": len(solved) / len(per_task["success"]),
                "mean_steps": sum(steps) / len(steps) if steps else math.nan,
                "mean_lower_bound": sum(bounds) / len(bounds) if bounds else math.nan,
                "steps_over_bound": (
                    sum(s / b for s, b in zip(steps, bounds, strict=True)) / len(steps)
                    if steps
                    else math.nan
                ),
                "seconds_per_task": sum(r["seconds_per_task"] for r in group) / len(group),
                "seed": "all",
                "success_rate_std": float(rates.std()),
                "per_task": per_task,
            }
        )
    return pooled


def steps_over_bound(result: dict[str, Any], tasks: TensorDictBase) -> float:
    """Mean over the solved tasks of steps taken / the task's lower bound (``nan`` if none)."""
    solved = torch.tensor(result["success"], dtype=torch.bool)
    if not bool(solved.any()) or "lower_bound" not in tasks.keys():
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


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[str] = RESULT_COLUMNS) -> str:
    """``rows`` as a markdown table with ``columns`` (floats with 2 decimals).

    Examples:
        >>> from dorp_rl.eval import format_table
        >>> row = dict(setting="1obj", method="random", low_level="gt", tasks=4,
        ...            success_rate=0.25, mean_steps=14.0, mean_lower_bound=2.0,
        ...            steps_over_bound=7.0, seconds_per_task=0.01)
        >>> print(format_table([row]).splitlines()[-1])
        | 1obj | random | gt | 4 | 0.25 | 14.00 | 2.00 | 7.00 | 0.01 |
    """
    missing = [c for c in columns if any(c not in r for r in rows)]
    if missing:
        raise KeyError(f"rows lack the columns {missing} (expected {list(columns)}).")
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "---|" * len(columns),
    ]
    lines += ["| " + " | ".join(_show(r[c]) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def write_results(
    rows: Sequence[dict[str, Any]],
    directory: str | Path,
    figures: Sequence[str | Path] = (),
    *,
    columns: Sequence[str] = RESULT_COLUMNS,
    sections: Sequence[str] = (),
) -> tuple[Path, Path]:
    """Writes ``results.csv`` and ``results.md`` (``columns``, by default
    :data:`RESULT_COLUMNS`) into ``directory``.

    ``sections`` (markdown) follow the table in ``results.md``, then ``figures``
    (pictures in ``directory``).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = directory / "results.csv", directory / "results.md"
    with csv_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    md_path.write_text(
        "# Results\n\nSuccess rate, mean steps of the solved tasks next to their mean lower "
        "bound (sum of Manhattan distances), and mean of steps / bound over them.\n\n"
        + format_table(rows, columns)
        + "\n"
        + "".join(f"\n{section.rstrip()}\n" for section in sections)
        + "".join(f"\n![{Path(f).stem}]({Path(f).name})\n" for f in figures)
    )
    return csv_path, md_path


#: the columns of a run's timing table
TIMING_COLUMNS: tuple[str, ...] = ("setting", "stage", "does", "seconds", "this_command")


def describe_stage(stage: str) -> str:
    """What a stage of a run folder does, in words (``codes:arbitrary`` -> ``train codes
    (arbitrary weight)``)."""
    name, _, rest = stage.partition(":")
    variant = {"arbitrary": "arbitrary weight", "identity": "identity weight", "full": "full graph"}
    if name == "play":
        return "collect play data"
    if name == "codes":
        return "train codes" + (f" ({variant.get(rest, rest)})" if rest else "")
    if name == "graph":
        return "build graph" + (f" ({variant.get(rest, rest)})" if rest else "")
    if name == "world_model":
        return "train video model"
    if name == "evaluate":
        method, _, level = rest.partition(":")
        return f"evaluate {method}" + (f" ({level})" if level else "")
    if name == "pictures":
        return "draw code maps, histogram and GIFs"
    return stage


def format_timings(rows: Sequence[dict[str, Any]]) -> str:
    """Timing rows (:data:`TIMING_COLUMNS`) as a markdown table with totals per setting
    and overall."""
    lines = ["| " + " | ".join(TIMING_COLUMNS) + " |", "|" + "---|" * len(TIMING_COLUMNS)]
    totals: dict[str, float] = {}
    for r in rows:
        lines.append(
            f"| {r['setting']} | {r['stage']} | {r['does']} | {r['seconds']:.1f} | "
            f"{r['this_command']} |"
        )
        totals[r["setting"]] = totals.get(r["setting"], 0.0) + r["seconds"]
    for setting, seconds in totals.items():
        lines.append(f"| {setting} | total | every stage | {seconds:.1f} | |")
    lines.append(f"| all | total | every stage | {sum(totals.values()):.1f} | |")
    return "\n".join(lines)


def format_time_by_kind(rows: Sequence[dict[str, Any]]) -> str:
    """What dominates a run: the seconds of timing rows summed by what their stages do
    (over settings), largest first, with each kind's share of all stage seconds.

    Examples:
        >>> rows = [
        ...     {"setting": "1obj", "does": "train video model", "seconds": 30.0},
        ...     {"setting": "2obj", "does": "train video model", "seconds": 50.0},
        ...     {"setting": "2obj", "does": "train codes", "seconds": 20.0},
        ... ]
        >>> print(format_time_by_kind(rows))
        | does | settings | seconds | share |
        |---|---|---|---|
        | train video model | 2 | 80.0 | 80% |
        | train codes | 1 | 20.0 | 20% |
    """
    seconds: dict[str, float] = {}
    settings: dict[str, set[str]] = {}
    for r in rows:
        seconds[r["does"]] = seconds.get(r["does"], 0.0) + float(r["seconds"])
        settings.setdefault(r["does"], set()).add(r["setting"])
    total = sum(seconds.values())
    lines = ["| does | settings | seconds | share |", "|---|---|---|---|"]
    for does, spent in sorted(seconds.items(), key=lambda item: -item[1]):
        share = f"{100 * spent / total:.0f}%" if total > 0 else "-"
        lines.append(f"| {does} | {len(settings[does])} | {spent:.1f} | {share} |")
    return "\n".join(lines)


def write_timings(rows: Sequence[dict[str, Any]], directory: str | Path) -> tuple[Path, Path]:
    """Writes ``timings.csv`` and ``timings.md`` (:data:`TIMING_COLUMNS`: per stage of
    each setting its wall-clock seconds and whether this command ran it (``ran``) or
    reused it from an earlier command (``reused``)) into ``directory``; ``timings.md``
    also sums them by what the stages do (:func:`format_time_by_kind`)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = directory / "timings.csv", directory / "timings.md"
    with csv_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=TIMING_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    md_path.write_text(
        "# Wall-clock per stage\n\nSeconds each stage took when it ran (stages reused from "
        "an earlier command keep the time they took then).\n\n"
        + format_timings(rows)
        + "\n\n## Where the time went\n\nThe same seconds summed by what the stages do, "
        "over the settings, largest first.\n\n" + format_time_by_kind(rows) + "\n"
    )
    return csv_path, md_path
