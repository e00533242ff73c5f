"""Latency of DORP's policy call against a reference checkout, measured in the same run.

The library's DORP policy (:func:`~dorp_rl.policies.make_dorp_policy` with the env's
profile, oracle codes, the true dynamics as the low level) runs seeded tasks of
rearrangement (2 and 3 objects) and key-wall; every policy call is timed (loop,
graph search, both planners), and so is every call of the waypoint planner alone. Each
measurement runs in a fresh worker process, alternating between this checkout and the
reference one (``--reference``: the root of another checkout with its own ``.venv``;
which of the two runs first alternates too),
so a change to the loop or the planning path is compared with the code before it on
the same machine at the same time; the ratio of the medians is taken pair by pair and
its median printed. Only the timings differ between the two: both run the same tasks
with the same seeds, and the worker prints a digest of the actions taken, which must
match when the change keeps the behaviour.

    .venv/bin/python benchmarks/dorp_step_latency.py --reference ../old-checkout --pairs 3
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

SETTINGS = {
    "2obj": ("rearrangement", {"num_objects": 2}),
    "3obj": ("rearrangement", {"num_objects": 3}),
    "keywall": ("key-wall", {}),
}


def worker(setting: str, tasks: int, steps: int, threads: int) -> dict:
    """Times one setting in this process (the library it imports is the one measured)."""
    import torch

    from dorp_rl.data import collect_play_data
    from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
    from dorp_rl.eval import make_task_set
    from dorp_rl.planners import CodeGraph
    from dorp_rl.policies import make_dorp_policy

    torch.set_num_threads(threads)
    name, kwargs = SETTINGS[setting]
    make = ObjectRearrangementEnv if name == "rearrangement" else KeyWallEnv
    env = make(batch_size=(tasks,), seed=0, **kwargs)
    oracle = OracleCodeEncoder(env)
    graph = CodeGraph.from_play_data(collect_play_data(env, 20_000, seed=0), oracle)
    policy = make_dorp_policy(env, oracle, graph, seed=0)
    calls: dict[str, list[float]] = {"policy": [], "waypoint planner": []}

    def timed(module, label):
        forward = module.forward

        def run(*args, **kwargs):
            start = time.perf_counter()
            out = forward(*args, **kwargs)
            calls[label].append(time.perf_counter() - start)
            return out

        module.forward = run

    timed(policy.waypoint_planner, "waypoint planner")
    timed(policy, "policy")
    task = make_task_set(env, tasks, seed=1).select("state", "goal_state")
    td = env.reset(task, set_state=True)
    rollout = env.rollout(steps, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    digest = hashlib.sha1(rollout["action"].numpy().tobytes()).hexdigest()[:12]
    return {
        "policy_ms": 1000 * statistics.median(calls["policy"]),
        "planner_ms": 1000 * statistics.median(calls["waypoint planner"]),
        "planner_calls": len(calls["waypoint planner"]),
        "solved": int(rollout["next", "success"].any(-2).sum()),
        "actions": digest,
    }


def measure(python: str, root: Path, args: argparse.Namespace, setting: str) -> dict:
    command = [
        python,
        str(Path(__file__).resolve()),
        "--worker",
        setting,
        "--tasks",
        str(args.tasks),
        "--steps",
        str(args.steps),
        "--threads",
        str(args.threads),
    ]
    out = subprocess.run(command, cwd=root, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, help="root of the checkout to compare with")
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--pairs", type=int, default=3, help="alternating runs of each")
    parser.add_argument("--tasks", type=int, default=8, help="tasks (rows) per run")
    parser.add_argument("--steps", type=int, default=60, help="policy calls per run")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--worker", choices=list(SETTINGS), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.tasks, args.steps, args.threads)))
        return
    here = Path(__file__).resolve().parents[1]
    runs = {"this": (sys.executable, here)}
    if args.reference is not None:
        root = args.reference.resolve()
        python = root / ".venv" / "bin" / "python"
        if not python.exists():
            raise SystemExit(f"--reference {root} has no .venv/bin/python (run make there).")
        runs["reference"] = (str(python), root)
    print(f"{args.tasks} tasks x {args.steps} policy calls, {args.threads} thread(s)")
    for setting in args.settings:
        results: dict[str, list[dict]] = {name: [] for name in runs}
        for pair in range(args.pairs):  # A B, B A, ...: neither always runs first
            order = list(runs.items()) if pair % 2 == 0 else list(runs.items())[::-1]
            for name, (python, root) in order:
                results[name].append(measure(python, root, args, setting))
        for name, rows in results.items():
            policy = statistics.median(r["policy_ms"] for r in rows)
            planner = statistics.median(r["planner_ms"] for r in rows)
            first = rows[0]
            print(
                f"{setting:8s} {name:9s} policy call {policy:7.1f} ms, waypoint planner "
                f"{planner:7.1f} ms ({first['planner_calls']} calls), solved "
                f"{first['solved']}/{args.tasks}, actions {first['actions']}"
            )
        if "reference" in results:
            ratios = [
                a["policy_ms"] / b["policy_ms"]
                for a, b in zip(results["this"], results["reference"], strict=True)
            ]
            planner_ratios = [
                a["planner_ms"] / b["planner_ms"]
                for a, b in zip(results["this"], results["reference"], strict=True)
            ]
            same = results["this"][0]["actions"] == results["reference"][0]["actions"]
            print(
                f"{setting:8s} this / reference: policy call {statistics.median(ratios):.3f}x, "
                f"waypoint planner {statistics.median(planner_ratios):.3f}x (median of "
                f"{args.pairs} pairs); same actions: {same}"
            )


if __name__ == "__main__":
    main()
