"""How the video model's cost per frame depends on how many frames one call gets, and
what chunking the calls of :class:`~dorp_rl.envs.VideoModelEnv` saves in a batched
evaluation.

What is measured, in CPU seconds of this process (so other work on a shared machine
does not inflate them):

- ``predict``: :meth:`~dorp_rl.modules.VideoPredictionModel.predict` on the same 8192
  frames (from reset states of the env), in calls of 128 to 8192 frames; per frame, and
  as a ratio to the fastest call size;
- ``VF-RS window``: VF-RS (1000 candidates x 14 steps) on 10 tasks side by side for 14
  batched steps through ``VideoModelEnv`` with ``chunk_size=None`` (every imagined step
  in one call: up to 10,000 frames) and with the default
  :data:`~dorp_rl.envs.planning.DEFAULT_PREDICT_CHUNK`; seconds per batched step and
  their ratio, measured in the same run;
- ``same frames``: one imagined step of a ``[10, 1000]`` batch both ways, and how many
  predicted frames differ (chunking must not change what the planner sees).

The model is a trained checkpoint (``--checkpoint``) or an untrained one of the default
preset (the cost does not depend on the weights).

    .venv/bin/python benchmarks/predict_chunking.py --objects 3 --threads 1 \
        --checkpoint runs/paper-w2/3obj/world_model/checkpoints/last.pt
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from dorp_rl.envs import ObjectRearrangementEnv, VideoModelEnv
from dorp_rl.envs.planning import DEFAULT_PREDICT_CHUNK
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.modules import VideoModelConfig, VideoPredictionModel
from dorp_rl.policies import VisualForesightPolicy
from dorp_rl.trainers import load_video_model

CALL_SIZES = (128, 512, 1024, 2048, 8192)
TASKS = 10


def _model(env: ObjectRearrangementEnv, checkpoint: Path | None) -> VideoPredictionModel:
    if checkpoint is not None:
        return load_video_model(checkpoint, env).eval()
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
    return VideoPredictionModel(env.num_actions, palette, VideoModelConfig.default()).eval()


def predict_cost(model: VideoPredictionModel, env: ObjectRearrangementEnv) -> dict[int, float]:
    """CPU milliseconds per frame of ``predict`` by frames per call."""
    generator = torch.Generator().manual_seed(0)
    frames = env.reset()["pixels"]
    pick = torch.randint(0, frames.shape[0], (max(CALL_SIZES),), generator=generator)
    frames = frames[pick]
    actions = torch.randint(0, env.num_actions, (frames.shape[0], 1), generator=generator)
    model.predict(frames[:128], actions[:128])  # warm-up
    cost = {}
    for size in CALL_SIZES:
        start = time.process_time()
        for first in range(0, frames.shape[0], size):
            model.predict(frames[first : first + size], actions[first : first + size])
        cost[size] = (time.process_time() - start) / frames.shape[0] * 1000
    return cost


def window_cost(
    model: VideoPredictionModel, objects: int, chunk_size: int | None, steps: int
) -> float:
    """CPU seconds per batched step of VF-RS on ``TASKS`` tasks side by side."""
    env = ObjectRearrangementEnv(num_objects=objects, batch_size=(TASKS,), seed=0)
    tasks = make_task_set(env, TASKS, seed=0)
    planning = VideoModelEnv(model, env.num_actions, chunk_size=chunk_size)
    policy = VisualForesightPolicy(planning, "rs", seed=0)
    start = time.process_time()
    result = evaluate_policy(env, policy, tasks, max_steps=steps, tasks_per_rollout=TASKS, seed=0)
    return (time.process_time() - start) / max(result["steps"])


def differing_frames(model: VideoPredictionModel, env: ObjectRearrangementEnv) -> int:
    """Frames of one imagined ``[TASKS, 1000]`` step that differ with and without chunks."""
    generator = torch.Generator().manual_seed(1)
    first = env.reset()["pixels"][:TASKS]
    frames = first.unsqueeze(1).expand(TASKS, 1000, *first.shape[-3:])
    actions = torch.randint(0, env.num_actions, (TASKS, 1000, 1), generator=generator)
    whole = VideoModelEnv(model, env.num_actions, chunk_size=None, deduplicate=False)
    chunked = VideoModelEnv(model, env.num_actions, deduplicate=False)
    one, other = whole.predict_frames(frames, actions), chunked.predict_frames(frames, actions)
    return int((one != other).flatten(2).any(-1).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=3, help="blocks in the rearrangement env")
    parser.add_argument("--checkpoint", type=Path, default=None, help="a world-model checkpoint")
    parser.add_argument("--steps", type=int, default=14, help="batched steps of the VF window")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    env = ObjectRearrangementEnv(num_objects=args.objects, batch_size=(64,), seed=0)
    model = _model(env, args.checkpoint)

    per_frame = predict_cost(model, env)
    fastest = min(per_frame.values())
    print("| frames per predict call | CPU ms per frame | / fastest |\n|---|---|---|")
    for size, ms in per_frame.items():
        print(f"| {size} | {ms:.3f} | {ms / fastest:.2f}x |")

    window = {
        "none": window_cost(model, args.objects, None, args.steps),
        str(DEFAULT_PREDICT_CHUNK): window_cost(
            model, args.objects, DEFAULT_PREDICT_CHUNK, args.steps
        ),
    }
    ratio = window["none"] / window[str(DEFAULT_PREDICT_CHUNK)]
    print(
        f"\nVF-RS on {TASKS} tasks side by side, {args.steps} batched steps, CPU s per step: "
        f"chunk_size=None {window['none']:.2f}, chunk_size={DEFAULT_PREDICT_CHUNK} "
        f"{window[str(DEFAULT_PREDICT_CHUNK)]:.2f} ({ratio:.2f}x faster)"
    )
    differing = differing_frames(model, env)
    print(f"same frames: {TASKS * 1000 - differing} of {TASKS * 1000} ({differing} differ)")
    if args.json is not None:
        results = {
            "per_frame_ms": per_frame,
            "window_s_per_step": window,
            "speedup": ratio,
            "differing_frames": differing,
        }
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
