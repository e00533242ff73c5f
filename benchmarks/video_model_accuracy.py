"""Trains the video prediction model and prints its open-loop accuracy and wall-clock.

The goal: on 3-object rearrangement, 14-step open-loop rollouts from
held-out play data (another seed) must match the true frame exactly in >= 95% of the
sequences. Prints the exact-configuration accuracy and pixel MSE at every step 1..14
(deterministic mode), the evaluations made during training, and the training time.
Interrupted runs continue with ``--resume``.

    python benchmarks/video_model_accuracy.py --num-objects 3 --steps 6000 --threads 1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from dorp_rl.modules import VideoModelConfig
from dorp_rl.trainers import WorldModelConfig, WorldModelTrainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="rearrangement")
    parser.add_argument("--num-objects", type=int, default=3)
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--num-frames", type=int, default=100_000)
    parser.add_argument("--model-preset", default="default", choices=["small", "default"])
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    parser.add_argument("--out-dir", type=Path, default=None)
    parser.add_argument("--resume", action="store_true", help="continue the last checkpoint")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    name = args.env if args.env != "rearrangement" else f"rearrangement{args.num_objects}"
    out_dir = args.out_dir or Path("outputs/world_model") / f"{name}-seed{args.seed}"
    preset = {
        "rearrangement": WorldModelConfig.rearrangement,
        "key-wall": WorldModelConfig.key_wall,
        "key-corridor": WorldModelConfig.key_corridor,
    }[args.env]
    overrides = {"num_objects": args.num_objects} if args.env == "rearrangement" else {}
    cfg = preset(
        **overrides,
        num_steps=args.steps,
        num_frames=args.num_frames,
        model=VideoModelConfig.preset(args.model_preset),
        batch_size=args.batch_size,
        seed=args.seed,
        out_dir=str(out_dir),
        progress=False,
    )
    start = time.perf_counter()
    trainer = WorldModelTrainer(cfg)
    setup = time.perf_counter() - start
    params = sum(p.numel() for p in trainer.model.parameters())
    print(
        f"{name}: {params} parameters, {len(trainer.buffer)} play frames, "
        f"torch threads {torch.get_num_threads()}, set-up {setup:.0f}s",
        flush=True,
    )
    result = trainer.train(resume=args.resume)
    seconds = time.perf_counter() - start
    for row in trainer.evaluations:
        steps = sorted(
            (k for k in row if k.startswith("exact_accuracy_step")),
            key=lambda k: int(k.rsplit("step", 1)[1]),
        )
        accs = "  ".join(f"{k.rsplit('step', 1)[1]}: {row[k]:.3f}" for k in steps)
        print(f"  step {int(row['step']):6d}  exact accuracy at open-loop step {accs}")
    evaluation = result["evaluation"]
    print(f"final (step {result['step']}, {evaluation['num_sequences']} held-out sequences):")
    print("  step   exact   pixel MSE")
    for h, (acc, mse) in enumerate(
        zip(evaluation["exact_accuracy"], evaluation["pixel_mse"], strict=True), start=1
    ):
        print(f"  {h:4d}   {acc:.3f}   {mse:9.5f}")
    last = evaluation["exact_accuracy_last"]
    print(
        f"{name}: {evaluation['horizon']}-step exact accuracy {last:.3f} "
        f"(goal >= 0.95: {'met' if last >= 0.95 else 'NOT met'}); "
        f"wall-clock {seconds / 60:.1f} min this run ({result['step']} steps)"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"setting": name, "seconds": seconds, "parameters": params, **evaluation}
        args.json.write_text(json.dumps(payload, indent=2, default=float))


if __name__ == "__main__":
    main()
