"""Visual-foresight baselines (VF-RS, VF-CEM) on a seeded task set: success and steps.

For each number of objects, planning model and variant, runs
:class:`~dorp_rl.policies.VisualForesightPolicy` (pixel L2 to the goal image, 1000
candidates x 14 steps; by default the best full sequence by its last frame is executed
open loop, the paper's description of VF) on the same ``--tasks`` tasks
of :func:`~dorp_rl.eval.make_task_set` through :func:`~dorp_rl.eval.evaluate_policy`,
and prints success rate, mean steps of the successful tasks next to their mean lower
bound (sum of Manhattan distances), and the wall-clock, with the paper's Table 1 figure
(which used an SV2P video model) beside it.

Planning models: ``gt`` (:class:`~dorp_rl.envs.GroundTruthModelEnv`, the true dynamics)
and ``video`` (:class:`~dorp_rl.envs.VideoModelEnv` over a trained
:class:`~dorp_rl.modules.VideoPredictionModel`, read from ``--checkpoint``'s template,
``{k}`` standing for the number of objects; train one with
``benchmarks/video_model_accuracy.py --num-objects k``).

    python benchmarks/visual_foresight.py --objects 1 2 --models gt video --tasks 50
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from bench_threads import add_threads_argument

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, VideoModelEnv
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.policies import VisualForesightPolicy
from dorp_rl.trainers import load_video_model

#: Table 1 of the paper (success rate with an SV2P model), by variant and objects.
PAPER = {"rs": {1: 0.83, 2: 0.58, 3: 0.25, 5: 0.00}, "cem": {1: 1.00, 2: 0.60, 3: 0.30, 5: 0.10}}
DEFAULT_CHECKPOINT = "outputs/world_model/rearrangement{k}-seed0/checkpoints/last.pt"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--models", nargs="+", choices=["gt", "video"], default=["gt", "video"])
    parser.add_argument("--variants", nargs="+", choices=["rs", "cem"], default=["rs", "cem"])
    parser.add_argument("--tasks", type=int, default=50)
    parser.add_argument("--task-seed", type=int, default=0)
    parser.add_argument(
        "--task-slice",
        nargs=2,
        type=int,
        default=None,
        metavar=("START", "STOP"),
        help="run only tasks[START:STOP] of the --tasks set (to split a run across processes)",
    )
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--max-steps", type=int, default=None, help="default: the env's limit")
    parser.add_argument(
        "--tasks-per-rollout", type=int, default=None, help="default: 10 gt, 1 video"
    )
    parser.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT, help="'{k}': objects")
    add_threads_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="planner seed")
    parser.add_argument(
        "--step-aggregation",
        choices=["final", "min"],
        default="final",
        help="how a sequence's per-step pixel distances make its score. final: score the "
        "last frame, execute the whole sequence (the paper's VF); min: score the closest "
        "frame, execute up to it (the authors' goal step)",
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    print(
        f"{args.tasks} tasks (seed {args.task_seed}), {args.candidates} candidates x "
        f"{args.planning_horizon} steps, open loop, step aggregation "
        f"{args.step_aggregation!r}; "
        f"torch threads {torch.get_num_threads()}"
    )
    print(
        f"{'objects':>7s} {'model':>5s} {'variant':>7s} {'success':>7s} {'paper':>5s} "
        f"{'steps':>6s} {'bound':>6s} {'limit':>5s} {'minutes':>7s}"
    )
    results = []
    for k in args.objects:
        env = ObjectRearrangementEnv(num_objects=k, batch_size=(), batch_locked=False, seed=0)
        tasks = make_task_set(env, args.tasks, seed=args.task_seed)
        if args.task_slice is not None:
            tasks = tasks[args.task_slice[0] : args.task_slice[1]]
        for model_name in args.models:
            if model_name == "gt":
                planning_env = GroundTruthModelEnv(env)
            else:
                model = load_video_model(args.checkpoint.format(k=k), env)
                planning_env = VideoModelEnv(model, env.num_actions)
            per_rollout = args.tasks_per_rollout or (10 if model_name == "gt" else 1)
            for variant in args.variants:
                policy = VisualForesightPolicy(
                    planning_env,
                    variant,
                    planning_horizon=args.planning_horizon,
                    num_candidates=args.candidates,
                    seed=args.seed,
                    step_aggregation=args.step_aggregation,
                )
                result = evaluate_policy(
                    env,
                    policy,
                    tasks,
                    max_steps=args.max_steps,
                    tasks_per_rollout=per_rollout,
                )
                paper = PAPER[variant].get(k, math.nan)
                print(
                    f"{k:7d} {model_name:>5s} {'VF-' + variant.upper():>7s} "
                    f"{result['success_rate']:7.2f} {paper:5.2f} {result['mean_steps']:6.1f} "
                    f"{result['mean_lower_bound']:6.1f} {result['max_steps']:5d} "
                    f"{result['seconds'] / 60:7.1f}",
                    flush=True,
                )
                results.append(
                    {
                        "objects": k,
                        "model": model_name,
                        "variant": variant,
                        "task_seed": args.task_seed,
                        "task_slice": args.task_slice,
                        **result,
                    }
                )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
