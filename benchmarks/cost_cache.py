"""DORP's evaluation with the planning costs' caches against the same run without them.

What is measured
----------------
The costs of DORP's planners keep what they computed between planning calls, keyed by
the bytes of the frame (``CodeMatchCost``: codes of each frame; ``ObjectMapCost`` and the
blurred ``PixelDistanceCost`` of the goal-image phase: the cost of each (frame, goal)
pair). A policy plans from nearly the same state many times, most of all in a goal phase
that does not get closer, so most frames come back. This script runs the same seeded
DORP evaluation twice per repeat on codes and a graph from a run folder: ``cached`` (the
policy as :func:`~dorp_rl.policies.make_dorp_policy` builds it) and ``uncached`` (every
cache of the policy's costs emptied and set to hold nothing, so each call computes all of
its frames), alternating, and prints the seconds of each, their ratio, and whether the two
evaluations ended every task the same way in the same steps.

Usage (a run folder of ``dorp reproduce`` or ``dorp evaluate``)::

    .venv/bin/python benchmarks/cost_cache.py runs/6obj/6obj-seed0 --setting 6obj --tasks 10
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.eval.settings import SETTINGS
from dorp_rl.planners import CodeGraph
from dorp_rl.planners.costs.caches import KeyedCache
from dorp_rl.policies import make_dorp_policy
from dorp_rl.trainers import load_encoder


def without_caches(policy: torch.nn.Module) -> int:
    """Empties every cost cache of ``policy`` and makes it hold nothing; returns how many."""
    count = 0
    for module in policy.modules():
        cache = getattr(module, "cache", None)
        if isinstance(cache, KeyedCache):
            cache.clear()
            cache.size = 0
            count += 1
    return count


def evaluate(args: argparse.Namespace, cached: bool) -> tuple[float, list]:
    setting = SETTINGS[args.setting]
    env = setting.make_env(batch_size=(args.tasks_per_rollout,), seed=args.seed)
    encoder = load_encoder(args.run / "codes" / "checkpoints" / "last.pt", env)
    graph = CodeGraph.load(args.run / "graph.pt", encoder=encoder)
    policy = make_dorp_policy(env, encoder, graph, seed=args.seed)
    if not cached and without_caches(policy) == 0:
        raise SystemExit("the policy's costs hold no cache: nothing to compare.")
    tasks = make_task_set(setting.make_env(), args.tasks, seed=args.task_seed)
    start = time.perf_counter()
    result = evaluate_policy(
        env, policy, tasks, tasks_per_rollout=args.tasks_per_rollout, seed=args.seed
    )
    seconds = time.perf_counter() - start
    ends = list(zip(result["success"], result["steps"], strict=True))
    return seconds, ends


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="folder with codes/ and graph.pt")
    parser.add_argument("--setting", required=True, choices=sorted(SETTINGS))
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--task-seed", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tasks-per-rollout", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for repeat in range(args.repeats):
        with_cache, ends_cached = evaluate(args, cached=True)
        without, ends_plain = evaluate(args, cached=False)
        solved = sum(bool(s) for s, _ in ends_cached)
        print(
            f"repeat {repeat}: {args.setting}, {args.tasks} tasks ({solved} solved): cached "
            f"{with_cache:.1f} s, uncached {without:.1f} s, ratio {with_cache / without:.2f}; "
            f"same endings and steps: {ends_cached == ends_plain}"
        )


if __name__ == "__main__":
    main()
