"""Trains the video prediction model and prints its open-loop accuracy and wall-clock.

The goal: on 3-object rearrangement, 14-step open-loop rollouts from
held-out play data (another seed) must match the true frame exactly in >= 95% of the
sequences. Prints the exact-configuration accuracy and pixel MSE at every step 1..14
(deterministic mode), the evaluations made during training, and the training time.
Interrupted runs continue with ``--resume``.

Then the rare events: on held-out windows (``--event-frames`` play frames of another
seed) that hold an event (a transition changing more cells than an ordinary step: in
the key rooms the key taken and the door opened), the open-loop accuracy, and the share
of the event transitions themselves that the model predicts exactly one step ahead from
the true frame (for key-wall: the door opens when the key is taken). ``--checkpoint``
evaluates a trained model instead of training one.

    python benchmarks/video_model_accuracy.py --num-objects 3 --steps 6000 --threads 1
    python benchmarks/video_model_accuracy.py --env key-wall --model-preset small --steps 2000 \
        --out-dir outputs/world_model/key-wall-events-seed0 --threads 1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from bench_threads import add_threads_argument

from dorp_rl.checkpoint import load_checkpoint
from dorp_rl.data import SequenceSampler, changed_pixels, collect_play_data, event_transitions
from dorp_rl.metrics.world_model import open_loop_accuracy
from dorp_rl.modules import VideoModelConfig, VideoPredictionModel
from dorp_rl.trainers import WorldModelConfig, WorldModelTrainer, load_video_model
from dorp_rl.trainers.windows import HELD_OUT_SEED_OFFSET, event_windows
from dorp_rl.validation import derive_seed


@torch.no_grad()
def event_check(
    model: VideoPredictionModel, cfg: WorldModelConfig, frames: int, max_windows: int = 512
) -> dict[str, float]:
    """Accuracy on the rare events of ``frames`` held-out play transitions (another seed).

    Returns the open-loop exact accuracy at steps 1 / mid / H of up to ``max_windows``
    windows holding an event, and ``event_step_exact``: the share of the event
    transitions predicted exactly one step ahead from the true frame.
    """
    env = cfg.make_env(batch_size=(cfg.num_envs,))
    buffer = collect_play_data(
        env,
        frames,
        seed=derive_seed(cfg.seed, HELD_OUT_SEED_OFFSET),
        trajectory_length=cfg.trajectory_length,
        progress=False,
    )
    out: dict[str, float] = {"event_windows": 0.0, "event_transitions": 0.0}
    windows = event_windows(
        buffer, cfg.horizon, max_windows, torch.Generator().manual_seed(cfg.seed)
    )
    if windows is None:
        return out
    result = open_loop_accuracy(model, windows)
    out["event_windows"] = float(result["num_sequences"])
    for h in sorted({1, (cfg.horizon + 1) // 2, cfg.horizon}):
        out[f"event_window_exact_step{h}"] = result["exact_accuracy"][h - 1]
    index = event_transitions(changed_pixels(buffer.storage)).nonzero().squeeze(-1)
    steps = buffer[index]
    model.eval()
    pred = model.rollout(steps["pixels"], steps["action"].unsqueeze(1), deterministic=True)
    exact = (pred[:, 0] == steps["next", "pixels"]).flatten(1).all(-1)
    out["event_transitions"] = float(len(index))
    out["event_step_exact"] = float(exact.float().mean())
    return out


def print_event_check(name: str, check: dict[str, float]) -> None:
    """One line per figure of :func:`event_check`."""
    if not check["event_windows"]:
        print(f"{name}: no held-out window holds an event")
        return
    accs = "  ".join(
        f"{k.rsplit('step', 1)[1]}: {v:.3f}"
        for k, v in check.items()
        if k.startswith("event_window_exact_step")
    )
    print(
        f"{name}: {int(check['event_windows'])} held-out event windows, exact accuracy at "
        f"open-loop step {accs}"
    )
    print(
        f"{name}: {int(check['event_transitions'])} held-out event transitions predicted "
        f"exactly one step ahead: {check['event_step_exact']:.3f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="rearrangement")
    parser.add_argument("--num-objects", type=int, default=3)
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--num-frames", type=int, default=100_000)
    parser.add_argument("--model-preset", default="default", choices=["small", "default"])
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    add_threads_argument(parser)
    parser.add_argument("--out-dir", type=Path, default=None)
    parser.add_argument("--resume", action="store_true", help="continue the last checkpoint")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    parser.add_argument(
        "--event-share",
        type=float,
        default=None,
        help="least share of training windows holding an event (default: the preset's, "
        "0.25 for key-wall, 0 otherwise)",
    )
    parser.add_argument(
        "--event-frames", type=int, default=100_000, help="held-out play frames of the event check"
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="evaluate this trained world model (its own config) instead of training",
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.checkpoint:
        evaluate_checkpoint(args)
        return

    name = args.env if args.env != "rearrangement" else f"rearrangement{args.num_objects}"
    out_dir = args.out_dir or Path("outputs/world_model") / f"{name}-seed{args.seed}"
    preset = {
        "rearrangement": WorldModelConfig.rearrangement,
        "key-wall": WorldModelConfig.key_wall,
        "key-corridor": WorldModelConfig.key_corridor,
    }[args.env]
    overrides = {"num_objects": args.num_objects} if args.env == "rearrangement" else {}
    if args.event_share is not None:
        overrides["event_share"] = args.event_share
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
        f"{name}: {params} parameters, {len(trainer.buffer)} play frames, event share "
        f"{cfg.event_share}, torch threads {torch.get_num_threads()}, set-up {setup:.0f}s",
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
        events = "  ".join(
            f"{k.rsplit('step', 1)[1]}: {row[f'event_{k}']:.3f}"
            for k in steps
            if f"event_{k}" in row
        )
        if events:  # the trainer's held-out event windows (event_share > 0)
            accs += f"; on {int(row['event_num_sequences'])} event windows {events}"
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
    check = event_check(trainer.model, cfg, args.event_frames)
    print_event_check(name, check)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "setting": name,
            "seconds": seconds,
            "parameters": params,
            **evaluation,
            **check,
        }
        args.json.write_text(json.dumps(payload, indent=2, default=float))


def evaluate_checkpoint(args: argparse.Namespace) -> None:
    """Held-out accuracy (the trainer's windows) and the event check of a trained model."""
    cfg = WorldModelConfig.from_dict(load_checkpoint(args.checkpoint)["config"])
    env = cfg.make_env(batch_size=(cfg.num_envs,))
    model = load_video_model(args.checkpoint, env)
    held_out = collect_play_data(
        env,
        cfg.eval_frames,
        seed=derive_seed(cfg.seed, HELD_OUT_SEED_OFFSET),
        trajectory_length=cfg.trajectory_length,
        sampler=SequenceSampler(cfg.horizon),
        progress=False,
    )
    held_out.set_rng(torch.Generator().manual_seed(cfg.seed))  # the trainer's windows
    windows = held_out.sample(cfg.eval_sequences)
    result = open_loop_accuracy(model, windows)
    accs = "  ".join(f"{h}: {a:.3f}" for h, a in enumerate(result["exact_accuracy"], start=1))
    name = str(args.checkpoint)
    print(f"{name}: event share {cfg.event_share}, {result['num_sequences']} held-out windows")
    print(f"{name}: exact accuracy at open-loop step {accs}")
    check = event_check(model, cfg, args.event_frames)
    print_event_check(name, check)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**result, **check}, indent=2, default=float))


if __name__ == "__main__":
    main()
