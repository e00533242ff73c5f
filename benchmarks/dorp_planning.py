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
    python benchmarks/dorp_planning.py --settings 5obj --dorp.reenter True --dorp.max-misses 2
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
import tyro

from dorp_rl.config import carry_changes
from dorp_rl.data import collect_play_data
from dorp_rl.envs import OracleCodeEncoder
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.eval.settings import SETTINGS, Setting
from dorp_rl.planners import CodeGraph
from dorp_rl.policies import DORPConfig, make_dorp_policy
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


def codes_and_graph(setting: Setting, args: Any, env) -> tuple[Any, CodeGraph, dict]:
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


def run(setting_name: str, low_level: str, args: Args) -> dict[str, Any]:
    setting = SETTINGS[setting_name]
    batch = args.tasks_per_rollout
    env = setting.make_env(batch_size=(batch,), seed=args.seed)
    encoder, graph, timings = codes_and_graph(setting, args, env)
    if low_level == "gt":
        level: Any = "gt"
    else:
        path = args.video_checkpoint.format(name=video_name(setting))
        level = load_video_model(path, env)
    # the setting's own DORP config, with the fields changed on the command line
    config = carry_changes(
        DORPConfig.for_env(setting.env, num_objects=setting.num_objects), args.dorp, DORPConfig()
    )
    cem = {} if args.top_k is None else {"top_k": args.top_k}
    policy = make_dorp_policy(
        env, encoder, graph, low_level=level, config=config, seed=args.seed, **cem
    )
    tasks = make_task_set(env, args.tasks, seed=args.task_seed)
    if args.task_ids is not None:
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
        "action_persistence": getattr(policy.waypoint_planner, "action_persistence", None),
        "task_ids": args.task_ids,
        "dorp": policy.config.to_dict(),
        "solved": [bool(x) for x in result["success"]],
        "steps": [int(x) for x in result["steps"]],
        "lower_bounds": [int(x) for x in tasks["lower_bound"]],
        **timings,
    }


@dataclass
class Args:
    """DORP on seeded task sets per setting and low level; every DORP setting is
    ``--dorp.<field>`` (DORPConfig), over each setting's own config."""

    settings: tuple[Literal[tuple(SETTINGS)], ...] = ("2obj",)  # type: ignore[valid-type]
    """the settings to run"""
    low_level: tuple[Literal["gt", "video"], ...] = ("gt",)
    """gt: the true dynamics; video: the video model of --video-checkpoint"""
    codes: Literal["trained", "oracle"] = "trained"
    """trained codes of the setting's preset, or oracle codes of the true positions"""
    oracle_cell: int = 4
    """region side of oracle codes"""
    code_seed: int = 0
    """seed of the trained codes"""
    tasks: int = 50
    task_seed: int = 0
    task_ids: tuple[int, ...] | None = None
    """run only these tasks of the --tasks task set (to look at chosen tasks again)"""
    seed: int = 0
    """seed of the planners"""
    max_steps: int | None = None
    """step limit of a task (None: the env's)"""
    tasks_per_rollout: int = 10
    top_k: int | None = None
    """CEM elites (None: CEM's default)"""
    threads: int = 1
    """torch threads (1: one per job; on a shared 2-core CPU more made steps far slower)"""
    progress: bool = False
    out_dir: Path = Path("outputs")
    """folder of the codes, play data and graphs"""
    video_checkpoint: str = "outputs/world_model/{name}-seed0/checkpoints/last.pt"
    """video model per setting; {name} is rearrangement<k>, key-wall or key-corridor"""
    json: Path | None = None
    """append the rows here"""
    dorp: DORPConfig = field(default_factory=DORPConfig)
    """DORP's settings: those changed here replace each setting's own"""


def main() -> None:
    args = tyro.cli(Args, description=__doc__.splitlines()[0])
    if args.tasks % args.tasks_per_rollout:
        raise SystemExit("--tasks must be a multiple of --tasks-per-rollout")
    if args.task_ids is not None and not all(0 <= i < args.tasks for i in args.task_ids):
        raise SystemExit(f"--task-ids must lie in [0, {args.tasks}), got {args.task_ids}.")
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
