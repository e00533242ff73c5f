"""Seconds per batched planning step of every evaluation in a run folder, and how much
slower each method plans through the video model than with the true dynamics.

An evaluation runs its tasks in chunks of ``tasks_per_rollout``, each chunk one batched
``env.rollout`` that lasts until its slowest task is done (solved, or at the step limit).
Its batched steps are therefore the sum over chunks of the longest task's steps, and its
stage seconds divided by them are the cost of one policy call on the whole batch: the
figure that says what a method costs per step, apart from how many steps it needed.
Everything is read from the run's ``stages.json`` files; nothing is run.

    .venv/bin/python benchmarks/evaluation_step_cost.py runs/paper-w2
    .venv/bin/python benchmarks/evaluation_step_cost.py runs/paper-w2 --json costs.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def batched_steps(steps: list[int], per: int) -> int:
    """Batched steps of an evaluation whose tasks (``steps`` each) ran ``per`` at a time:
    per chunk, its longest task's."""
    return sum(max(steps[i : i + per]) for i in range(0, len(steps), per))


def evaluation_costs(run: Path) -> list[dict[str, Any]]:
    """One row per finished evaluation stage of ``run`` (a run folder, or a
    ``reproduce --paper`` folder with one sub-run per setting)."""
    folders = [run] if (run / "stages.json").exists() else []
    folders += sorted(p for p in run.iterdir() if (p / "stages.json").exists())
    if not folders:
        raise SystemExit(f"{run} holds no stages.json (neither it nor its sub-folders).")
    rows = []
    for folder in folders:
        stages = json.loads((folder / "stages.json").read_text())
        for key, record in stages.items():
            if not key.startswith("evaluate:") or record.get("config") is None:
                continue
            summary, config = record["summary"], record["config"]
            steps = summary["per_task"]["steps"]
            per = config["tasks_per_rollout"]
            batched = batched_steps(steps, per)
            rows.append(
                {
                    "setting": summary["setting"],
                    "method": summary["method"],
                    "low_level": summary["low_level"],
                    "tasks": len(steps),
                    "success_rate": summary["success_rate"],
                    "batched_steps": batched,
                    "seconds": float(record["seconds"]),
                    "seconds_per_batched_step": float(record["seconds"]) / batched,
                }
            )
    return rows


def slowdowns(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per setting and method with both low levels: seconds per batched step through the
    video model over those with the true dynamics."""
    by = {(r["setting"], r["method"], r["low_level"]): r for r in rows}
    out = []
    for (setting, method, level), row in by.items():
        gt = by.get((setting, method, "gt"))
        if level != "world-model" or gt is None:
            continue
        ratio = row["seconds_per_batched_step"] / gt["seconds_per_batched_step"]
        out.append({"setting": setting, "method": method, "video_over_gt": ratio})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder (runs/<name>)")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    rows = evaluation_costs(args.run)
    print("| setting | method | low level | tasks | success | batched steps | s | s per step |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['setting']} | {r['method']} | {r['low_level']} | {r['tasks']} | "
            f"{r['success_rate']:.2f} | {r['batched_steps']} | {r['seconds']:.0f} | "
            f"{r['seconds_per_batched_step']:.3f} |"
        )
    ratios = slowdowns(rows)
    if ratios:
        print("\n| setting | method | per step, video model over true dynamics |")
        print("|---|---|---|")
        for r in ratios:
            print(f"| {r['setting']} | {r['method']} | {r['video_over_gt']:.0f}x |")
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows, "slowdowns": ratios}, indent=2) + "\n")


if __name__ == "__main__":
    main()
