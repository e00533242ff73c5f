"""Latency of one planning call, 1000 candidates x 14 steps, and what dominates it.

What is measured
----------------
One :class:`~dorp_rl.planners.RandomShootingPlanner` call (``num_candidates`` random
sequences of ``planning_horizon`` steps, pixel-L2 cost to the goal, one acting env) through:

- ``ground truth``: :class:`~dorp_rl.envs.GroundTruthModelEnv` (true dynamics and
  renderer of ``ObjectRearrangementEnv``);
- ``world model``: :class:`~dorp_rl.envs.VideoModelEnv` wrapping the project's
  :class:`~dorp_rl.modules.VideoPredictionModel`, trained (``--checkpoint``, a
  ``WorldModelTrainer`` checkpoint) or freshly initialised at a preset's size
  (``--preset``; latency does not depend on the weights). The env predicts each
  distinct (frame, action) pair once; ``no dedup`` is the same call predicting every
  candidate's frame;
- ``bare forward``: the model's ``predict`` on the same frames, ``planning_horizon``
  calls of ``num_candidates`` frames each, nothing else: the floor a planner through
  this model cannot beat. ``bare forward x1`` is one call on all
  ``num_candidates * planning_horizon`` frames, for reference.

With ``--cem`` the :class:`~dorp_rl.planners.CategoricalCEMPlanner` (3 ``optim_steps``) is
timed too. Each number is the median of ``--repeats`` calls after a warm-up call. A
breakdown of the world-model call splits it into model ``predict``, the cost, and the
rest (TorchRL ``step`` / ``step_mdp``, sampling, stacking), timed by wrappers in the
same call; ``--profile`` adds torch.profiler's top operators.

With ``--encoder`` (a representation checkpoint) DORP's waypoint call is timed too:
random shooting through the video model with the waypoint cost of
:func:`~dorp_rl.policies.make_waypoint_cost` as the DORP policy uses it in rearrangement
(the :class:`~dorp_rl.planners.CodeMatchCost`, which encodes every distinct imagined
frame, plus the goal image's blurred pixel distance at ``--waypoint-goal-weight``), once
without the cost's cache and once with the codes of an earlier call cached, and with the
code term alone.

Goals: at most 1 s per pixel-cost call and 1.5 s per waypoint call through the video
model on this 2-core CPU.

Usage::

    .venv/bin/python benchmarks/planning_latency.py               # 2 threads
    .venv/bin/python benchmarks/planning_latency.py --threads 1 --cem --profile
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from bench_threads import add_threads_argument
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from dorp_rl.envs import ObjectRearrangementEnv
from dorp_rl.envs.planning import GroundTruthModelEnv, VideoModelEnv
from dorp_rl.modules import VideoModelConfig, VideoPredictionModel
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import make_waypoint_cost
from dorp_rl.trainers import load_encoder, load_video_model

GOAL_SECONDS = 1.0
WAYPOINT_GOAL_SECONDS = 1.5


def build_model(env: ObjectRearrangementEnv, args: argparse.Namespace) -> tuple[nn.Module, str]:
    """The trained model of ``--checkpoint``, or an untrained one of ``--preset``'s size."""
    if args.checkpoint is not None:
        model = load_video_model(args.checkpoint, env)
        return model, f"VideoPredictionModel from {args.checkpoint}"
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
    config = VideoModelConfig.preset(args.preset)
    model = VideoPredictionModel(env.num_actions, palette, config).eval()
    return model, f"VideoPredictionModel, {args.preset} preset (untrained)"


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


class Timed:
    """Accumulates the time spent in a callable (a model's predict, a cost)."""

    def __init__(self, fn: Callable) -> None:
        self.fn, self.seconds, self.calls = fn, 0.0, 0

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start
            self.calls += 1


class TimedCost(TensorDictModuleBase):
    """A cost module timed by a :class:`Timed` wrapper; same keys and step aggregation."""

    def __init__(self, cost: TensorDictModuleBase) -> None:
        super().__init__()
        self.cost, self.timer = cost, Timed(cost)
        self.in_keys, self.out_keys = cost.in_keys, cost.out_keys
        self.step_aggregation = cost.step_aggregation

    def forward(self, rollout: TensorDictBase) -> TensorDictBase:
        return self.timer(rollout)


class TimedModel:
    def __init__(self, model: nn.Module) -> None:
        self.model, self.timer = model, Timed(model.predict)

    def predict(self, pixels, action, deterministic=True):
        return self.timer(pixels, action, deterministic=deterministic)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_threads_argument(parser)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--objects", type=int, default=3, help="blocks in the rearrangement env")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--checkpoint", type=Path, default=None, help="a world-model checkpoint")
    parser.add_argument("--preset", choices=("small", "default"), default="default")
    parser.add_argument("--cem", action="store_true", help="also time CEM (optim_steps=3)")
    parser.add_argument("--profile", action="store_true", help="torch.profiler top operators")
    parser.add_argument(
        "--encoder",
        type=Path,
        default=None,
        help="a representation checkpoint: also time a DORP waypoint call",
    )
    parser.add_argument(
        "--waypoint-goal-weight",
        type=float,
        default=0.003,
        help="the waypoint cost's goal-image weight (make_dorp_policy's in rearrangement)",
    )
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    env = ObjectRearrangementEnv(num_objects=args.objects, batch_size=(1,), seed=0)
    td = env.reset()
    n, h = args.candidates, args.planning_horizon
    model, description = build_model(env, args)
    num_params = sum(p.numel() for p in model.parameters())
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.objects}-object "
        f"rearrangement; {n} candidates x {h} steps, batch 1"
    )
    print(f"model: {description}, {num_params:,} parameters")

    def planner(cls, model_env, cost=None, **kwargs):
        return cls(
            model_env,
            cost or PixelDistanceCost(),
            planning_horizon=h,
            num_candidates=n,
            seed=0,
            **kwargs,
        )

    rows: list[tuple[str, float]] = []
    gt = planner(RandomShootingPlanner, GroundTruthModelEnv(env))
    rows.append(("RS call, ground truth", median_seconds(lambda: gt(td.clone()), args.repeats)))
    wm_env = VideoModelEnv(model, env.num_actions)
    wm = planner(RandomShootingPlanner, wm_env)
    rows.append(("RS call, world model", median_seconds(lambda: wm(td.clone()), args.repeats)))
    wm_plain = planner(
        RandomShootingPlanner, VideoModelEnv(model, env.num_actions, deduplicate=False)
    )
    no_dedup = (
        "RS call, world model, no dedup",
        median_seconds(lambda: wm_plain(td.clone()), args.repeats),
    )
    frames = td["pixels"].expand(n, 3, 16, 16).contiguous()
    actions = torch.randint(0, env.num_actions, (n, 1))

    def bare() -> None:
        for _ in range(h):
            model.predict(frames, actions, deterministic=True)

    rows.append((f"bare forward ({h} x {n} frames)", median_seconds(bare, args.repeats)))
    all_frames = frames.repeat(h, 1, 1, 1)
    all_actions = actions.repeat(h, 1)
    rows.append(
        (
            f"bare forward x1 ({h * n} frames)",
            median_seconds(lambda: model.predict(all_frames, all_actions), args.repeats),
        )
    )
    rows.append(no_dedup)
    if args.cem:
        cem_gt = planner(CategoricalCEMPlanner, GroundTruthModelEnv(env))
        cem_wm = planner(CategoricalCEMPlanner, wm_env)
        rows.append(
            (
                "CEM call (3 it.), ground truth",
                median_seconds(lambda: cem_gt(td.clone()), args.repeats),
            )
        )
        rows.append(
            (
                "CEM call (3 it.), world model",
                median_seconds(lambda: cem_wm(td.clone()), args.repeats),
            )
        )

    if args.encoder is not None:
        # DORP's waypoint step: every imagined frame is encoded and matched to a waypoint
        # code for one one-hot, the others kept. Without the cost's cache every distinct
        # frame is encoded; with it, frames encoded by an earlier call are not.
        encoder = load_encoder(args.encoder, env)
        waypoint_td = td.clone()
        waypoint_td["subgoal_code"] = encoder.encode(td["pixels"])
        mask = torch.zeros_like(waypoint_td["subgoal_code"], dtype=torch.bool)
        mask[..., 0] = True
        waypoint_td["subgoal_mask"] = mask
        variants = (
            ("no cache", 0, args.waypoint_goal_weight),
            ("cache warm", 2**18, args.waypoint_goal_weight),
            ("code term alone", 0, 0.0),
        )
        for label, cache, weight in variants:
            cost = make_waypoint_cost(encoder, waypoint_goal_weight=weight, cache_size=cache)
            call = planner(RandomShootingPlanner, wm_env, cost)
            seconds = median_seconds(lambda call=call: call(waypoint_td.clone()), args.repeats)
            rows.append((f"DORP waypoint call, world model, {label}", seconds))

    bare_s = rows[2][1]
    width = max(len(name) for name, _ in rows)
    print(f"\n{'':{width}s} {'ms':>9s} {'/ bare fwd':>11s}")
    for name, seconds in rows:
        print(f"{name:{width}s} {seconds * 1e3:9.1f} {seconds / bare_s:10.2f}x")
    wm_s = rows[1][1]
    verdict = "meets" if wm_s <= GOAL_SECONDS else "misses"
    print(
        f"\nworld-model call {wm_s:.2f} s: {verdict} the <= {GOAL_SECONDS:.0f} s goal; ground "
        f"truth is {wm_s / rows[0][1]:.1f}x faster than the world model."
    )
    if args.encoder is not None:
        waypoint_s = dict(rows)["DORP waypoint call, world model, no cache"]
        verdict = "meets" if waypoint_s <= WAYPOINT_GOAL_SECONDS else "misses"
        print(
            f"DORP waypoint call {waypoint_s:.2f} s without the cache: {verdict} the "
            f"<= {WAYPOINT_GOAL_SECONDS} s goal."
        )

    # Breakdown of one world-model call, timed by wrappers inside the call.
    timed_model = TimedModel(model)
    timed_cost = TimedCost(PixelDistanceCost())
    breakdown = planner(
        RandomShootingPlanner, VideoModelEnv(timed_model, env.num_actions), timed_cost
    )
    breakdown(td.clone())
    timed_model.timer.seconds = timed_cost.timer.seconds = 0.0
    start = time.perf_counter()
    breakdown(td.clone())
    total = time.perf_counter() - start
    predict_s, cost_s = timed_model.timer.seconds, timed_cost.timer.seconds
    other = total - predict_s - cost_s
    print("\nwhere a world-model call goes:")
    for name, seconds in (
        ("model predict", predict_s),
        ("pixel cost", cost_s),
        ("rest (step/step_mdp, sampling, stacking)", other),
    ):
        print(f"  {name:42s} {seconds * 1e3:8.1f} ms  {100 * seconds / total:5.1f} %")
    gt_timed_cost = TimedCost(PixelDistanceCost())
    gt_breakdown = planner(RandomShootingPlanner, GroundTruthModelEnv(env), gt_timed_cost)
    gt_breakdown(td.clone())
    gt_timed_cost.timer.seconds = 0.0
    start = time.perf_counter()
    gt_breakdown(td.clone())
    gt_total = time.perf_counter() - start
    print(
        f"ground-truth call: {gt_total * 1e3:.1f} ms, of which the pixel cost "
        f"{gt_timed_cost.timer.seconds * 1e3:.1f} ms and dynamics + TorchRL stepping the rest"
    )

    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            wm(td.clone())
        print("\ntorch.profiler, one world-model call (top operators by self CPU time):")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=10))


if __name__ == "__main__":
    main()
