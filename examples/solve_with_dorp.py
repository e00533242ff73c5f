"""Solve rearrangement tasks with DORP and save one episode, with its waypoints, as a PNG.

    python examples/solve_with_dorp.py                       # oracle codes: seconds
    dorp demo                                                # learns 2-object codes
    python examples/solve_with_dorp.py --encoder runs/demo/codes/checkpoints/last.pt

Builds a :class:`~dorp_rl.planners.CodeGraph` from random play data with the given codes
(learned ones from a representation checkpoint, or :class:`~dorp_rl.envs.OracleCodeEncoder`
codes read off the true positions), assembles :func:`~dorp_rl.policies.make_dorp_policy`
with the true dynamics as the low level, and runs ``--tasks`` seeded tasks with
``env.rollout``. The first episode's frames go to ``<out-dir>/episode.png`` (goal last),
and the log prints the mode and waypoint of every step of it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from dorp_rl.data import collect_play_data
from dorp_rl.envs import ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.planners import CodeGraph
from dorp_rl.policies import MODES, make_dorp_policy
from dorp_rl.trainers import load_encoder
from dorp_rl.viz import save_frame_strip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-objects", type=int, default=2)
    parser.add_argument("--encoder", type=Path, default=None, help="representation checkpoint")
    parser.add_argument("--play-frames", type=int, default=20_000)
    parser.add_argument("--tasks", type=int, default=5)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out-dir", type=Path, default=Path("outputs/solve_with_dorp"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    env = ObjectRearrangementEnv(num_objects=args.num_objects, batch_size=(args.tasks,), seed=0)
    encoder = OracleCodeEncoder(env) if args.encoder is None else load_encoder(args.encoder, env)
    play = collect_play_data(env, args.play_frames, seed=args.seed)
    graph = CodeGraph.from_play_data(play, encoder, progress=True)
    print(graph)
    policy = make_dorp_policy(env, encoder, graph, num_candidates=args.candidates, seed=args.seed)
    tasks = make_task_set(env, args.tasks, seed=args.seed)
    result = evaluate_policy(
        env, policy, tasks, tasks_per_rollout=args.tasks, report_keys=("dorp_replans",)
    )
    print(
        f"solved {sum(result['success'])} of {args.tasks} tasks; steps {result['steps']} "
        f"(lower bounds {tasks['lower_bound'].tolist()}); edges removed {result['dorp_replans']}"
    )

    # One episode again, step by step, to show what the policy does.
    td = env.reset(tasks.select("state", "goal_state"), set_state=True)
    rollout = env.rollout(
        int(result["steps"][0]), policy, tensordict=td, auto_reset=False, break_when_any_done=False
    )
    names = {value: key for key, value in MODES.items()}
    for t in range(rollout.shape[1]):
        step = rollout[0, t]
        print(
            f"step {t:3d}: mode {names[int(step['dorp_mode'])]:8s} code "
            f"{step['code'].tolist()} waypoint {step['subgoal_code'].tolist()} "
            f"goal {step['goal_code'].tolist()}"
        )
    frames = torch.cat([rollout["pixels"][0], rollout["goal_pixels"][0, :1]])
    path = save_frame_strip(frames, args.out_dir / "episode.png")
    print(f"episode written to {path}")


if __name__ == "__main__":
    main()
