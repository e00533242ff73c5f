"""DORP on seeded task sets: success, steps against the lower bound, replans, seconds.

For every setting it takes codes trained by the library's presets (training them, with
their play data, when ``--out-dir`` does not hold them yet), builds the code graph over
that play data, assembles :func:`~dorp_rl.policies.make_dorp_policy` with the chosen low
level, and runs it on ``--tasks`` tasks of :func:`~dorp_rl.eval.make_task_set` through
:func:`~dorp_rl.eval.evaluate_policy`. It prints, per setting: success rate, mean steps
of the solved tasks, their mean lower bound, the ratio of the two, edges removed
(replans) per task, tasks given up, and seconds per task, with the paper's figure.

Settings: ``1obj``, ``2obj``, ``3obj`` (one graph per one-hot), ``5obj`` (groups
``(0, 1)`` and ``(2, 3, 4)``, 1400-step limit), ``3obj-full`` and ``5obj-full`` (the
full-graph ablation), ``keywall`` and ``keycorridor`` (agent and key bit in one group).
Low levels: ``gt`` (the true dynamics) and ``video`` (a video model from
``--video-checkpoint``; train one with ``benchmarks/video_model_accuracy.py``).
``--codes oracle`` swaps the learned codes for :class:`~dorp_rl.envs.OracleCodeEncoder`.

    python benchmarks/dorp_planning.py --settings 1obj 2obj 3obj --low-level gt --threads 1
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import torch

from dorp_rl.data import collect_play_data
from dorp_rl.envs import OracleCodeEncoder
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.eval.settings import SETTINGS, Setting
from dorp_rl.planners import CodeGraph
from dorp_rl.policies import make_dorp_policy
from dorp_rl.trainers import (
    RepresentationConfig,
    RepresentationTrainer,
    load_encoder,
    load_video_model,
)


def codes_name(setting: Setting) -> str:
    """Folder name of a setting's codes and play data: rearrangement<k>, keywall, ..."""
    if setting.env == "rearrangement":
        return f"rearrangement{setting.num_objects}"
    return setting.env.replace("-", "")


def video_name(setting: Setting) -> str:
    """The run name ``benchmarks/video_model_accuracy.py`` gives this env's video model."""
    return codes_name(setting) if setting.env == "rearrangement" else setting.env


def _switch(name: str, value: str) -> dict[str, bool | str]:
    """``auto`` (the env profile's setting: nothing passed) / ``on`` / ``off`` (/ ``goal``)
    as the ``make_dorp_policy`` keyword ``name``."""
    chosen = {"auto": None, "on": True, "off": False, "goal": "goal"}[value]
    return {} if chosen is None else {name: chosen}


def codes_and_graph(setting: Setting, args: argparse.Namespace, env) -> tuple[Any, CodeGraph, dict]:
    """The encoder (trained or oracle) and its code graph, from disk when already built."""
    name = f"{codes_name(setting)}-seed{args.code_seed}"
    play_dir = args.out_dir / "play" / name
    cfg = RepresentationConfig.for_env(
        setting.env,
        setting.num_objects,
        seed=args.code_seed,
        out_dir=str(args.out_dir / "codes" / name),
        data_dir=str(play_dir),
        progress=False,
    )
    timings: dict[str, float] = {}
    if args.codes == "oracle":
        encoder = OracleCodeEncoder(env, cell_size=args.oracle_cell)
    else:
        checkpoint = Path(cfg.out_dir) / "checkpoints" / "last.pt"
        if not checkpoint.exists():
            start = time.perf_counter()
            RepresentationTrainer(cfg).train()
            timings["train_codes_s"] = time.perf_counter() - start
        encoder = load_encoder(checkpoint, env)
    groups = setting.groups
    tag = groups if isinstance(groups, str) else "-".join("".join(map(str, g)) for g in groups)
    tag += "-completed" if setting.completes_graph() else ""
    graph_path = args.out_dir / "graphs" / f"{name}-{args.codes}-{tag}.pt"
    if graph_path.exists():
        graph = CodeGraph.load(graph_path, encoder=encoder, env_config=env.config())
    else:
        buffer = collect_play_data(
            cfg.make_env(batch_size=(cfg.num_envs,)),
            cfg.num_frames,
            directory=play_dir,
            seed=cfg.seed,
            trajectory_length=cfg.trajectory_length,
        )
        start = time.perf_counter()
        graph = setting.make_graph(buffer, encoder)
        timings["graph_s"] = time.perf_counter() - start
        graph.save(graph_path)
    return encoder, graph, timings


def run(setting_name: str, low_level: str, args: argparse.Namespace) -> dict[str, Any]:
    setting = SETTINGS[setting_name]
    batch = args.tasks_per_rollout
    env = setting.make_env(batch_size=(batch,), seed=args.seed)
    encoder, graph, timings = codes_and_graph(setting, args, env)
    if low_level == "gt":
        level: Any = "gt"
    else:
        path = args.video_checkpoint.format(name=video_name(setting))
        level = load_video_model(path, env)
    policy = make_dorp_policy(
        env,
        encoder,
        graph,
        low_level=level,
        planner=args.planner,
        planning_horizon=args.planning_horizon,
        num_candidates=args.candidates,
        waypoint_budget=args.waypoint_budget,
        max_removed_edges=args.max_removed_edges,
        forget_blocked_edges=not args.keep_removed_edges,
        **_switch("reenter", args.reenter),
        **_switch("replan_on_miss", args.replan_on_miss),
        **_switch("waypoint_first_arrival", args.waypoint_first_arrival),
        **args.dorp,
        order=args.order,
        goal_planner=args.goal_planner,
        seed=args.seed,
        **(
            {}
            if args.waypoint_goal_weight is None
            else {"waypoint_goal_weight": args.waypoint_goal_weight}
        ),
        **({} if args.top_k is None else {"top_k": args.top_k}),
        **(
            {}
            if args.action_persistence is None
            else {"action_persistence": args.action_persistence}
        ),
        **({} if args.max_misses is None else {"max_misses": args.max_misses}),
        **(
            {}
            if args.waypoint_step_penalty is None
            else {"waypoint_step_penalty": args.waypoint_step_penalty}
        ),
    )
    tasks = make_task_set(env, args.tasks, seed=args.task_seed)
    if args.task_ids is not None:
        if not all(0 <= i < args.tasks for i in args.task_ids):
            raise SystemExit(f"--task-ids must lie in [0, {args.tasks}), got {args.task_ids}.")
        tasks = tasks[torch.tensor(args.task_ids)]
    result = evaluate_policy(
        env,
        policy,
        tasks,
        max_steps=args.max_steps,
        tasks_per_rollout=batch,
        progress=args.progress,
        report_keys=("dorp_replans", "dorp_failed"),
    )
    solved = torch.tensor(result["success"])
    steps = torch.tensor(result["steps"], dtype=torch.float32)
    bound = tasks["lower_bound"].float()
    ratio = float((steps[solved] / bound[solved]).mean()) if solved.any() else math.nan
    return {
        "setting": setting_name,
        "low_level": low_level,
        "codes": args.codes,
        "groups": graph.groups,
        "graph_nodes": [graph.num_nodes(g) for g in range(graph.num_groups)],
        "success_rate": result["success_rate"],
        "mean_steps": result["mean_steps"],
        "mean_lower_bound": result["mean_lower_bound"],
        "steps_over_bound": ratio,
        "replans_per_task": sum(result["dorp_replans"]) / len(tasks),
        "given_up": int(sum(result["dorp_failed"])),
        "seconds_per_task": result["seconds"] / len(tasks),
        "max_steps": result["max_steps"],
        "paper": setting.paper,
        "reenter": policy.config.reenter,
        "replan_on_miss": policy.config.replan_on_miss,
        "planner": args.planner,
        "waypoint_goal_weight": args.waypoint_goal_weight,
        "waypoint_step_penalty": args.waypoint_step_penalty,
        "waypoint_first_arrival": policy.config.waypoint_first_arrival,
        "max_misses": policy.config.max_misses,
        "action_persistence": getattr(policy.waypoint_planner, "action_persistence", None),
        "task_ids": args.task_ids,
        "dorp": args.dorp,
        "solved": [bool(x) for x in result["success"]],
        "steps": [int(x) for x in result["steps"]],
        "lower_bounds": [int(x) for x in tasks["lower_bound"]],
        **timings,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", nargs="+", choices=sorted(SETTINGS), default=["2obj"])
    parser.add_argument("--low-level", nargs="+", choices=["gt", "video"], default=["gt"])
    parser.add_argument("--codes", choices=["trained", "oracle"], default="trained")
    parser.add_argument("--oracle-cell", type=int, default=4, help="region side of oracle codes")
    parser.add_argument("--code-seed", type=int, default=0, help="seed of the trained codes")
    parser.add_argument("--tasks", type=int, default=50)
    parser.add_argument("--task-seed", type=int, default=0)
    parser.add_argument(
        "--task-ids",
        type=int,
        nargs="+",
        default=None,
        help="run only these tasks of the --tasks task set (to look at chosen tasks again)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the planners")
    parser.add_argument("--planner", choices=["rs", "cem"], default="rs")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--waypoint-budget", type=int, default=28)
    parser.add_argument("--max-removed-edges", type=int, default=128)
    parser.add_argument(
        "--max-misses",
        type=int,
        default=None,
        help="waypoint plans in a row that reach the waypoint nowhere before its edge is "
        "removed (default: make_dorp_policy's)",
    )
    parser.add_argument(
        "--keep-removed-edges",
        action="store_true",
        help="never restore a removed edge (the authors); default: restore a group's removed "
        "edges when another group reaches a waypoint",
    )
    parser.add_argument(
        "--reenter",
        choices=["auto", "on", "off", "goal"],
        default="auto",
        help="before removing a hop no other path replaces, leave its code over the edge "
        "that entered it and re-enter the code another way (goal: only when the goal phase "
        "stalls; auto: on in the key rooms, off in rearrangement)",
    )
    parser.add_argument(
        "--replan-on-miss",
        choices=["auto", "on", "off"],
        default="auto",
        help="cut a waypoint plan that reaches the waypoint nowhere to its first step "
        "(auto: in the key rooms)",
    )
    parser.add_argument(
        "--waypoint-first-arrival",
        choices=["auto", "on", "off"],
        default="auto",
        help="judge a waypoint plan at its first step reaching the waypoint (auto: the "
        "config's default)",
    )
    parser.add_argument(
        "--dorp",
        type=json.loads,
        default={},
        help="more DORPConfig fields as JSON, e.g. '{\"action_prior_mix\": 0.95}'",
    )
    parser.add_argument("--order", choices=["index", "nearest"], default="index")
    parser.add_argument("--goal-planner", choices=["rs", "cem"], default=None)
    parser.add_argument(
        "--action-persistence",
        type=float,
        default=None,
        help="random shooting: probability that a sampled action repeats the one before it "
        "(default: make_dorp_policy's)",
    )
    parser.add_argument("--top-k", type=int, default=None, help="CEM elites (default: CEM's)")
    parser.add_argument(
        "--waypoint-goal-weight",
        type=float,
        default=None,
        help="weight of the goal image's pixel distance in the waypoint cost "
        "(default: make_dorp_policy's)",
    )
    parser.add_argument(
        "--waypoint-step-penalty",
        type=float,
        default=None,
        help="cost per step of a frame at the waypoint: earlier arrival wins "
        "(default: make_dorp_policy's)",
    )
    parser.add_argument("--max-steps", type=int, default=None, help="default: the env's limit")
    parser.add_argument("--tasks-per-rollout", type=int, default=10)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (default 1: one per job; on a shared 2-core CPU more made steps far slower)",
    )
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--out-dir", type=Path, default=Path("outputs"))
    parser.add_argument(
        "--video-checkpoint",
        default="outputs/world_model/{name}-seed0/checkpoints/last.pt",
        help="video model per setting; {name} is rearrangement<k>, key-wall or key-corridor",
    )
    parser.add_argument("--json", type=Path, default=None, help="append the rows here")
    args = parser.parse_args()
    if args.tasks % args.tasks_per_rollout:
        parser.error("--tasks must be a multiple of --tasks-per-rollout")
    torch.set_num_threads(args.threads)
    header = (
        f"{'setting':<12} {'low':<6} {'success':>8} {'steps':>7} {'bound':>6} {'ratio':>6} "
        f"{'replans':>8} {'gave up':>8} {'s/task':>7}  paper"
    )
    print(header, flush=True)
    rows = []
    for low_level in args.low_level:
        for name in args.settings:
            row = run(name, low_level, args)
            rows.append(row)
            print(
                f"{name:<12} {low_level:<6} {row['success_rate']:>8.2f} {row['mean_steps']:>7.1f} "
                f"{row['mean_lower_bound']:>6.1f} {row['steps_over_bound']:>6.2f} "
                f"{row['replans_per_task']:>8.2f} {row['given_up']:>8d} "
                f"{row['seconds_per_task']:>7.2f}  {row['paper']}",
                flush=True,
            )
            if args.json is not None:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                with args.json.open("a") as f:
                    f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
