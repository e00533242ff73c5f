"""The encoder's inference path against its plain extractor, alone and inside DORP's waypoint call.

What is measured
----------------
In eval mode without gradients :class:`~dorp_rl.modules.DiscreteCodeEncoder` runs its
object extractor as :meth:`~dorp_rl.modules.DiscreteCodeEncoder.inference_extractor`
(BatchNorm folded into the convolutions, channels-last). ``reference`` is the plain
extractor (``encoder.fast_inference = False``), measured in the same run:

- ``encode``: :meth:`~dorp_rl.modules.DiscreteCodeEncoder.encode` of ``--frames`` play
  frames (codes of both paths are checked to be equal first);
- ``waypoint``: one DORP waypoint planning call through the true dynamics: random
  shooting (``--candidates`` x ``--planning-horizon``) with
  :class:`~dorp_rl.planners.CodeMatchCost` on one one-hot, for ``--batch`` rows of a
  seeded task set, its frame cache emptied before each call (the planned actions of
  both paths are checked to be equal first).

Fast and reference calls alternate, each figure is the median of ``--repeats`` calls
after a warm-up, and the ratio reference / fast is what to read on a shared machine.

Usage::

    .venv/bin/python benchmarks/encoder_inference.py --checkpoint outputs/codes/rearrangement5-seed0/checkpoints/last.pt --objects 5
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from bench_threads import add_threads_argument, parse_with_threads
from tensordict import TensorDict

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
from dorp_rl.eval import make_task_set
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.planners import CodeMatchCost, RandomShootingPlanner
from dorp_rl.trainers import load_encoder


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def alternate(encoder: DiscreteCodeEncoder, fn, repeats: int) -> tuple[float, float]:
    """Median seconds of ``fn`` with the fast path and with the plain extractor."""
    fast, reference = [], []
    for flag in (True, False):  # warm-up
        encoder.fast_inference = flag
        fn()
    for _ in range(repeats):
        for flag, times in ((True, fast), (False, reference)):
            encoder.fast_inference = flag
            times.append(timed(fn))
    encoder.fast_inference = True
    return statistics.median(fast), statistics.median(reference)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", help="representation checkpoint (default: untrained)")
    parser.add_argument("--objects", type=int, default=3)
    parser.add_argument("--frames", type=int, default=8192)
    parser.add_argument("--batch", type=int, default=2, help="acting rows per waypoint call")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--repeats", type=int, default=5)
    add_threads_argument(parser)
    args = parse_with_threads(parser)
    torch.manual_seed(0)

    env = ObjectRearrangementEnv(args.objects, batch_size=(args.batch,), seed=0)
    if args.checkpoint:
        encoder = load_encoder(args.checkpoint, env)
    else:
        encoder = DiscreteCodeEncoder(EncoderConfig.small((32,) * args.objects)).eval()
    single = ObjectRearrangementEnv(args.objects, batch_size=(), seed=0, batch_locked=False)
    frames = single.render_state(single.sample_states((args.frames,)))
    with torch.no_grad():
        fast_codes = encoder.encode(frames)
        encoder.fast_inference = False
        reference_codes = encoder.encode(frames)
        encoder.fast_inference = True
    agree = float((fast_codes == reference_codes).all(-1).float().mean())
    fast, reference = alternate(encoder, lambda: encoder.encode(frames), args.repeats)
    print(f"encode {args.frames} frames: codes equal on {agree:.4f} of frames")
    print(
        f"  fast {fast * 1e6 / args.frames:.1f} us/frame, reference "
        f"{reference * 1e6 / args.frames:.1f} us/frame: {reference / fast:.2f}x"
    )

    tasks = make_task_set(env, args.batch, seed=0)
    td = env.reset(
        TensorDict(state=tasks["state"], goal_state=tasks["goal_state"], batch_size=env.batch_size),
        set_state=True,
    )
    goal = encoder.encode(td["goal_pixels"])
    subgoal = encoder.encode(td["pixels"])
    subgoal[:, 0] = goal[:, 0]
    td["subgoal_code"] = subgoal
    cost = CodeMatchCost(encoder, onehots=[0])
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        cost,
        planning_horizon=args.planning_horizon,
        num_candidates=args.candidates,
    )

    def call() -> TensorDict:
        cost.cache.clear()
        torch.manual_seed(0)
        return planner(td.clone())

    encoder.fast_inference = True
    fast_out = call()
    encoder.fast_inference = False
    reference_out = call()
    same = bool(torch.equal(fast_out["action"], reference_out["action"]))
    key = planner.plan_cost_key
    gap = float((fast_out[key] - reference_out[key]).abs().max())
    fast, reference = alternate(encoder, call, args.repeats)
    # Equal codes give equal match terms; the confidence tie-break (1e-3 x probability)
    # differs by float rounding, which may pick another of several matching plans.
    print(
        f"waypoint call ({args.batch} rows, {args.candidates} x {args.planning_horizon}, "
        f"cache emptied): same first actions: {same}, plan costs differ by {gap:.1e}"
    )
    print(
        f"  fast {fast * 1e3:.0f} ms, reference {reference * 1e3:.0f} ms: {reference / fast:.2f}x"
    )


if __name__ == "__main__":
    main()
