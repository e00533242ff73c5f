"""DORP's goal-image phase alone: tasks that start with every code at the goal's.

In rearrangement a learned code covers many cells, some far apart, so after the code
graph's last waypoint a block may still be far from its goal place: the goal-image phase
(pixel and object-map distance to the goal image, plans through the true dynamics) has
to finish the task, and its stalls are most of the steps above the lower bound at 5 and
6 objects. This benchmark measures that phase on its own, with less noise than whole
tasks: each task's goal is drawn as ``make_task_set`` draws them, and its start puts
every block on a cell where the encoder gives the frame exactly the goal's codes (found
by moving one block at a time over the grid with the others at their goal places, then
drawing one such cell per block until the whole frame keeps the goal's codes), at least
``--min-distance`` cells from the goal in total. The policy then starts in the goal
phase. It prints success, mean steps of the solved tasks against their lower bound,
relaxed goal phases, and seconds, for each ``--dorp`` variant on the same tasks.

Codes and graphs come from ``benchmarks/dorp_planning.py``'s ``--out-dir`` (trained
there when missing).

    python benchmarks/dorp_goal_phase.py --settings 5obj --code-seed 1 --tasks 30 \
        --dorp '{}' '{"goal_action_prior_mix": 0.8}' --threads 1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import torch
from dorp_planning import codes_and_graph
from tensordict import TensorDict

from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.eval.settings import SETTINGS
from dorp_rl.policies import make_dorp_policy


@torch.no_grad()
def goal_phase_tasks(env, encoder, num_tasks: int, min_distance: int, seed: int = 0) -> TensorDict:
    """``num_tasks`` rearrangement tasks whose start frame has exactly the goal's codes."""
    encoder.eval()
    gen = torch.Generator().manual_seed(seed)
    size = env.observation_spec["pixels"].shape[-1]
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    cells = torch.stack([rows.flatten(), cols.flatten()], -1)
    pool = make_task_set(env, 8 * num_tasks, seed=seed)
    starts, goals = [], []
    for goal in pool["goal_state"]:
        goal_code = encoder(env.render_state(goal.unsqueeze(0)))[0][0]
        choices = []
        for block in range(goal.shape[0]):
            moved = goal.unsqueeze(0).repeat(cells.shape[0], 1, 1)
            moved[:, block] = cells
            moved = moved[~env.invalid_states(moved)]
            same = (encoder(env.render_state(moved))[0] == goal_code).all(-1)
            choices.append(moved[same][:, block])
        for _ in range(200):
            start = torch.stack([c[torch.randint(len(c), (1,), generator=gen)][0] for c in choices])
            if bool(env.invalid_states(start.unsqueeze(0))[0]):
                continue
            if int((start - goal).abs().sum()) < min_distance:
                continue
            if torch.equal(encoder(env.render_state(start.unsqueeze(0)))[0][0], goal_code):
                starts.append(start)
                goals.append(goal)
                break
        if len(starts) == num_tasks:
            break
    if len(starts) < num_tasks:
        raise RuntimeError(f"found {len(starts)} goal-phase tasks of {num_tasks} wanted.")
    state, goal_state = torch.stack(starts), torch.stack(goals)
    bound = env.lower_bound_steps(state, goal_state)
    return TensorDict(state=state, goal_state=goal_state, lower_bound=bound, batch_size=[num_tasks])


def run(setting_name: str, dorp: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    setting = SETTINGS[setting_name]
    env = setting.make_env(batch_size=(args.tasks_per_rollout,), seed=args.seed)
    encoder, graph, _ = codes_and_graph(setting, args, env)
    tasks = goal_phase_tasks(env, encoder, args.tasks, args.min_distance, args.task_seed)
    policy = make_dorp_policy(env, encoder, graph, low_level="gt", seed=args.seed, **dorp)
    start = time.perf_counter()
    out = evaluate_policy(
        env,
        policy,
        tasks,
        max_steps=args.max_steps,
        tasks_per_rollout=args.tasks_per_rollout,
        seed=args.seed,
    )
    seconds = time.perf_counter() - start
    bounds = tasks["lower_bound"].tolist()
    solved = [i for i, s in enumerate(out["success"]) if s]
    ratio = sum(out["steps"][i] / max(bounds[i], 1) for i in solved) / max(len(solved), 1)
    return {
        "setting": setting_name,
        "code_seed": args.code_seed,
        "dorp": dorp,
        "solved": len(solved),
        "tasks": args.tasks,
        "mean_steps": sum(out["steps"][i] for i in solved) / max(len(solved), 1),
        "mean_lower_bound": sum(bounds[i] for i in solved) / max(len(solved), 1),
        "steps_over_bound": ratio,
        "all_steps": sum(out["steps"]),
        "relaxed": sum(int(r.get("relaxed", 0)) for r in out["records"]),
        "seconds": seconds,
        "steps": out["steps"],
        "lower_bounds": bounds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", nargs="+", default=["5obj"])
    parser.add_argument("--code-seed", type=int, default=0)
    parser.add_argument("--tasks", type=int, default=30)
    parser.add_argument("--task-seed", type=int, default=7)
    parser.add_argument("--min-distance", type=int, default=6, help="cells, summed over blocks")
    parser.add_argument("--max-steps", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0, help="seed of the planners")
    parser.add_argument("--tasks-per-rollout", type=int, default=10)
    parser.add_argument(
        "--dorp", nargs="+", default=["{}"], help="DORPConfig fields as JSON, one per variant"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out-dir", type=Path, default=Path("outputs"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    args.codes = "trained"
    torch.set_num_threads(args.threads)
    rows = []
    print(f"{'setting':8} {'variant':40} {'solved':>7} {'steps':>6} {'bound':>6} "
          f"{'ratio':>6} {'all steps':>9} {'relaxed':>7} {'s':>6}")  # fmt: skip
    for setting in args.settings:
        for variant in args.dorp:
            row = run(setting, json.loads(variant), args)
            rows.append(row)
            print(
                f"{setting:8} {variant:40} {row['solved']:>3}/{row['tasks']:<3} "
                f"{row['mean_steps']:6.1f} {row['mean_lower_bound']:6.1f} "
                f"{row['steps_over_bound']:6.2f} {row['all_steps']:9d} {row['relaxed']:7d} "
                f"{row['seconds']:6.0f}",
                flush=True,
            )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
