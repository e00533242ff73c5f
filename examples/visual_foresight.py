"""Reach goal images with visual foresight (VF-CEM / VF-RS) and save the episode as a PNG.

    python examples/visual_foresight.py                          # true dynamics, 1 object
    dorp train-world-model --setting 2obj --name wm2                # a video model first
    python examples/visual_foresight.py --num-objects 2 \\
        --checkpoint runs/wm2/world_model/checkpoints/last.pt

Plans with pixel L2 to the goal through the ground-truth model (default) or a trained
video model (``--checkpoint``: a ``WorldModelTrainer`` checkpoint, which ``dorp
train-world-model`` writes), runs ``--tasks`` tasks with ``env.rollout`` and writes the first
episode's frames, goal last, to ``<out-dir>/episode.png``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, VideoModelEnv
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.policies import VisualForesightPolicy
from dorp_rl.trainers import load_video_model
from dorp_rl.viz import save_frame_strip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-objects", type=int, default=1)
    parser.add_argument("--variant", choices=["rs", "cem"], default="cem")
    parser.add_argument("--checkpoint", type=Path, default=None, help="a world-model checkpoint")
    parser.add_argument("--candidates", type=int, default=300)
    parser.add_argument("--tasks", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", type=Path, default=Path("outputs/visual_foresight"))
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1: one per job)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    env = ObjectRearrangementEnv(args.num_objects, batch_size=(), batch_locked=False, seed=0)
    if args.checkpoint is None:
        planning_env = GroundTruthModelEnv(env)
    else:
        planning_env = VideoModelEnv(load_video_model(args.checkpoint, env), env.num_actions)
    # VF-CEM refits to the best 2 % of the candidates (the paper's top_k=20 of 1000).
    elites = {"top_k": max(1, round(0.02 * args.candidates))} if args.variant == "cem" else {}
    policy = VisualForesightPolicy(
        planning_env, args.variant, num_candidates=args.candidates, seed=args.seed, **elites
    )

    # One episode by hand: a seeded task, env.rollout with the planner as the policy.
    tasks = make_task_set(env, args.tasks, seed=args.seed)
    td = env.reset(tasks[:1].select("state", "goal_state"), set_state=True)
    episode = env.rollout(env.max_steps, policy, tensordict=td, auto_reset=False)
    frames = torch.cat([episode["pixels"][0], episode["next", "pixels"][0, -1:], td["goal_pixels"]])
    path = save_frame_strip(frames, args.out_dir / "episode.png")
    print(
        f"first task: {episode.shape[-1]} steps, success {bool(episode['next', 'success'][0, -1])}"
    )
    print(f"frames (goal last): {path}")

    # All tasks through the evaluation harness.
    result = evaluate_policy(env, policy, tasks)
    print(
        f"VF-{args.variant.upper()} on {result['num_tasks']} tasks: success rate "
        f"{result['success_rate']:.2f}, mean steps {result['mean_steps']:.1f} "
        f"(lower bound {result['mean_lower_bound']:.1f})"
    )


if __name__ == "__main__":
    main()
