"""What an evaluation through a run's learned model costs, measured on its first steps.

For each setting of a ``dorp reproduce --paper`` folder that has a trained model
(``--model world-model``: the video model,
``<run>/<setting>/world_model/checkpoints/last.pt``; ``--model latent-model``: the latent
world model, ``<run>/<setting>/latent_model/checkpoints/last.pt``) and each method, this
runs the first chunk of the run's task set (``tasks_per_rollout`` tasks side by side, the
run's seeds, candidates and horizon) for ``--steps`` batched steps twice: planning with
the true dynamics and through the model. It times both in CPU seconds of this process
(one torch thread), so other work on a shared machine does not inflate them, and prints
per method:

- the CPU seconds per batched step of each, and their ratio;
- the batched steps and seconds of the evaluation with the true dynamics, from the
  run's own record of it;
- two estimates of the evaluation through the model, both as if it needed the
  steps the true dynamics needed (lower when the model makes the method solve fewer
  tasks): the model's cost per step measured here times those steps, and that
  ratio times the true dynamics' seconds;
- the seconds the run took for it through the model, where it has finished.

A step costs more later in a chunk than on its first plan, with either low level (the
true dynamics' run took 2-8x its first plan's cost times its steps at 3 and 5
objects): the first estimate misses that, the second carries it over as the true
dynamics showed it. At 1 object, where both evaluations finished, the first gave 43-44
and 71-74 s for VF-RS and VF-CEM, the second 80-92 and 186-229 s (three runs), against
95 and 253 s measured.

Nothing of the run is changed. The VF planners plan open loop, at most a planning horizon
(14 steps) at a time: time a multiple of it.

    .venv/bin/python benchmarks/model_planning_cost.py runs/paper-w2 --settings 3obj 5obj \
        --methods vf-rs vf-cem --steps 14 --threads 1 --model latent-model
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch
from evaluation_step_cost import batched_steps  # this folder is on the path of a script

from dorp_rl.eval import SETTINGS, evaluate_policy, make_task_set
from dorp_rl.eval.parallel import EvalSpec

VF_METHODS = ("vf-rs", "vf-cem")
#: --model: the run's sub-folder holding each kind of learned model
MODEL_FOLDERS = {"world-model": "world_model", "latent-model": "latent_model"}


def _cpu_seconds_per_step(spec: EvalSpec, tasks: Any, steps: int, seed: int) -> float:
    """CPU seconds per batched step of ``tasks`` run for at most ``steps`` steps (the
    chunk stops early when all its tasks are solved: its longest task's steps count)."""
    env = spec.make_env()
    policy = spec.make_policy(env)
    start = time.process_time()
    result = evaluate_policy(
        env, policy, tasks, max_steps=steps, tasks_per_rollout=spec.tasks_per_rollout, seed=seed
    )
    return (time.process_time() - start) / max(result["steps"])


def _batched_steps(record: dict, per: int) -> int | None:
    """Batched steps of a finished evaluation record: per chunk, its longest task's."""
    if not record.get("config"):
        return None
    return batched_steps(record["summary"]["per_task"]["steps"], per)


def planning_costs(
    run: Path, settings: list[str], methods: list[str], steps: int, model: str = "world-model"
) -> list[dict]:
    """One row per setting and method: see the module docstring. ``model`` is a key of
    :data:`MODEL_FOLDERS`."""
    rows = []
    for setting in settings:
        sub = run / setting
        checkpoint = sub / MODEL_FOLDERS[model] / "checkpoints" / "last.pt"
        if not checkpoint.is_file():
            print(f"{setting}: no {model} yet ({checkpoint}), left out")
            continue
        config = json.loads((sub / "config.json").read_text())
        stages = json.loads((sub / "stages.json").read_text())
        per = min(config["tasks"], config["tasks_per_rollout"])
        env = SETTINGS[setting].make_env(batch_size=(per,), seed=config["seed"])
        first_chunk = make_task_set(env, config["tasks"], seed=config["task_seed"])[:per]
        for method in methods:
            if method not in VF_METHODS:
                raise SystemExit(f"--methods: {method!r} is not one of {VF_METHODS}.")
            cost = {}
            for level, low_level in (("gt", "gt"), ("model", str(checkpoint))):
                spec = EvalSpec(
                    setting,
                    method,
                    low_level=low_level,
                    tasks_per_rollout=per,
                    candidates=config["candidates"],
                    planning_horizon=config["planning_horizon"],
                    seed=config["seed"],
                )
                cost[level] = _cpu_seconds_per_step(spec, first_chunk, steps, config["seed"])
            gt_record = stages.get(f"evaluate:{method}:gt") or {}
            model_record = stages.get(f"evaluate:{method}:{model}") or {}
            gt_steps = _batched_steps(gt_record, per)
            gt_seconds = gt_record.get("seconds") if gt_steps is not None else None
            ratio = cost["model"] / cost["gt"]
            rows.append(
                {
                    "setting": setting,
                    "method": method,
                    "gt_cpu_s_per_step": cost["gt"],
                    "model_cpu_s_per_step": cost["model"],
                    "ratio": ratio,
                    "gt_batched_steps": gt_steps,
                    "gt_seconds": gt_seconds,
                    "first_plan_estimate_seconds": None
                    if gt_steps is None
                    else cost["model"] * gt_steps,
                    "estimate_seconds": None if gt_seconds is None else ratio * gt_seconds,
                    "model_seconds": model_record.get("seconds")
                    if model_record.get("config")
                    else None,
                }
            )
            print(f"{setting} {method}: {rows[-1]}", flush=True)
    return rows


def _hours(seconds: float | None) -> str:
    if seconds is None:
        return "–"
    return f"{seconds:.0f} s" if seconds < 3600 else f"{seconds / 3600:.1f} h"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a reproduce --paper folder (runs/<name>)")
    parser.add_argument("--settings", nargs="+", default=["2obj", "3obj", "5obj"])
    parser.add_argument("--methods", nargs="+", default=list(VF_METHODS))
    parser.add_argument(
        "--steps", type=int, default=14, help="batched steps timed (a multiple of the horizon)"
    )
    parser.add_argument("--model", choices=sorted(MODEL_FOLDERS), default="world-model")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    if args.steps < 1:
        raise SystemExit(f"--steps must be >= 1, got {args.steps}.")
    torch.set_num_threads(args.threads)
    rows = planning_costs(args.run, args.settings, args.methods, args.steps, args.model)
    print(
        f"\n| setting | method | CPU s per step, true dynamics | {args.model} | ratio | "
        "evaluation, true dynamics | estimate: model cost x steps | estimate: ratio x "
        "seconds | measured through the model |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        gt = "–" if r["gt_seconds"] is None else f"{r['gt_batched_steps']} steps, "
        gt += "" if r["gt_seconds"] is None else _hours(r["gt_seconds"])
        print(
            f"| {r['setting']} | {r['method']} | {r['gt_cpu_s_per_step']:.3f} | "
            f"{r['model_cpu_s_per_step']:.2f} | {r['ratio']:.0f}x | "
            f"{gt} | {_hours(r['first_plan_estimate_seconds'])} | "
            f"{_hours(r['estimate_seconds'])} | {_hours(r['model_seconds'])} |"
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
