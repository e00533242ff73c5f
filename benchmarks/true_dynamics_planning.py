"""Planning through the true dynamics: the state fast path against the generic TorchRL path.

What is measured
----------------
One planning call of the visual-foresight baselines (``num_candidates`` x
``planning_horizon``, :class:`~dorp_rl.planners.PixelDistanceCost` to the goal image) for
a batch of ``--batch`` acting rows of k-object rearrangement, through
:class:`~dorp_rl.envs.GroundTruthModelEnv`, with
:class:`~dorp_rl.planners.RandomShootingPlanner` (VF-RS) and
:class:`~dorp_rl.planners.CategoricalCEMPlanner` (VF-CEM, 3 optimisation steps, top 20):

- ``fast``: what the planners do with a ``GroundTruthModelEnv``: candidates rolled out on
  raw states (``GroundTruthModelEnv.imagine_candidates``), the cost computed from the states
  (:class:`~dorp_rl.envs.planning.ImaginedFrames`: exact pixel distances from the frames'
  parts, distinct frames drawn only where a cost needs frames);
- ``reference``: the generic path, kept for every other planning env and measured in the
  same run (a ``GroundTruthModelEnv`` whose ``imagine_candidates`` returns ``None``):
  ``env.step`` / ``step_mdp`` per horizon step, every frame drawn and stacked, the
  cost's ``per_step_cost`` on the stacked frames. This is what planning through the
  true dynamics cost before the fast path.

Both paths are run on the same seeded calls, and the script checks that they return the
same actions and plan costs before timing them. Each figure is the median of
``--repeats`` calls after a warm-up call; fast and reference calls alternate, so that
load on a shared machine hits both alike. ``--costs`` adds DORP's costs: ``blur`` (pixel
distance with blurred terms of widths 1, 2, 4) and ``code`` (``CodeMatchCost`` with the
oracle encoder on one one-hot, its cache emptied before each call) and ``code-warm`` (the
same with the cache kept: the repeated seeded calls find every frame in it, the best case
of consecutive waypoint calls).

``--rollout-steps T`` also times whole episodes the way the evaluation runs the
baselines: ``env.rollout(T, VisualForesightPolicy(...))`` (open-loop execution, so rows
replan only when their plan runs out) on both paths, reported per env step of the batch,
after checking that both paths executed the same actions.

Usage::

    .venv/bin/python benchmarks/true_dynamics_planning.py                 # 1 thread
    .venv/bin/python benchmarks/true_dynamics_planning.py --objects 5 --costs pixel code
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from bench_threads import add_threads_argument
from tensordict import TensorDictBase

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeMatchCost,
    DiscreteMPCPlanner,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import VisualForesightPolicy


class SteppedModel(GroundTruthModelEnv):
    """The true dynamics without the fast path: the planners step it (generic TorchRL path)."""

    def imagine_candidates(self, td, actions, next_keys):
        return None


def make_cost(name: str, env: ObjectRearrangementEnv):
    if name == "pixel":
        return PixelDistanceCost()
    if name == "blur":
        return PixelDistanceCost(blur_sigmas=(1.0, 2.0, 4.0))
    # "code" and "code-warm" (the latter keeps the cache between calls).
    return CodeMatchCost(OracleCodeEncoder(env), onehots=[0])


def make_planner(variant: str, env, cost: str, args, reference: bool) -> DiscreteMPCPlanner:
    cls = RandomShootingPlanner if variant == "rs" else CategoricalCEMPlanner
    extra = {} if variant == "rs" else {"optim_steps": 3, "top_k": 20}
    return cls(
        SteppedModel(env) if reference else GroundTruthModelEnv(env),
        make_cost(cost, env),
        planning_horizon=args.planning_horizon,
        num_candidates=args.candidates,
        seed=0,
        **extra,
    )


def call(planner: DiscreteMPCPlanner, td: TensorDictBase, warm: bool = False) -> TensorDictBase:
    planner.set_seed(0)
    cache = getattr(planner.cost, "cache", None)
    if cache is not None and not warm:  # every call encodes its frames afresh
        cache.keys = None
    return planner(td.clone())


def time_pair(fast, reference, td, repeats: int, warm: bool) -> tuple[float, float]:
    """Medians (fast, reference) in seconds, calls alternating, after one warm-up each."""
    out_fast, out_ref = call(fast, td, warm), call(reference, td, warm)
    for key in ("action", "planner_plan", "planner_cost", "planner_length"):
        if not torch.equal(out_fast[key], out_ref[key]):
            raise AssertionError(f"the fast and reference paths differ in {key!r}")
    times: dict[str, list[float]] = {"fast": [], "reference": []}
    for _ in range(repeats):
        for name, planner in (("fast", fast), ("reference", reference)):
            start = time.perf_counter()
            call(planner, td, warm)
            times[name].append(time.perf_counter() - start)
    return statistics.median(times["fast"]), statistics.median(times["reference"])


def time_rollouts(k: int, variant: str, args) -> tuple[float, float]:
    """Seconds per env step of a VF episode of ``args.rollout_steps`` steps: (fast, reference)."""
    seconds, actions = [], []
    for reference in (False, True):
        env = ObjectRearrangementEnv(num_objects=k, batch_size=(args.batch,), seed=0)
        policy = VisualForesightPolicy(
            SteppedModel(env) if reference else GroundTruthModelEnv(env),
            variant,
            planning_horizon=args.planning_horizon,
            num_candidates=args.candidates,
            seed=0,
        )
        start = time.perf_counter()
        steps = env.rollout(args.rollout_steps, policy, break_when_any_done=False)
        seconds.append((time.perf_counter() - start) / args.rollout_steps)
        actions.append(steps["action"])
    if not torch.equal(actions[0], actions[1]):
        raise AssertionError("the fast and reference paths executed different actions")
    return seconds[0], seconds[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_threads_argument(parser)
    parser.add_argument("--objects", type=int, nargs="+", default=[1, 5])
    parser.add_argument("--batch", type=int, default=10, help="acting rows planned per call")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--variants", nargs="+", choices=("rs", "cem"), default=["rs", "cem"])
    parser.add_argument(
        "--costs", nargs="+", choices=("pixel", "blur", "code", "code-warm"), default=["pixel"]
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--rollout-steps", type=int, default=0, help="also time VF episodes of this many steps"
    )
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); "
        f"{args.candidates} candidates x {args.planning_horizon} steps, batch {args.batch}; "
        f"median of {args.repeats} calls"
    )
    print(
        f"\n{'objects':>7s} {'planner':>7s} {'cost':>9s} {'fast ms':>9s} {'ref. ms':>9s} {'ratio':>7s}"
    )
    for k in args.objects:
        env = ObjectRearrangementEnv(num_objects=k, batch_size=(args.batch,), seed=0)
        td = env.reset()
        td["subgoal_code"] = OracleCodeEncoder(env).encode(td["goal_pixels"])
        for cost in args.costs:
            for variant in args.variants:
                fast = make_planner(variant, env, cost, args, reference=False)
                reference = make_planner(variant, env, cost, args, reference=True)
                warm = cost == "code-warm"
                fast_s, ref_s = time_pair(fast, reference, td, args.repeats, warm)
                print(
                    f"{k:7d} {variant:>7s} {cost:>9s} {fast_s * 1e3:9.1f} {ref_s * 1e3:9.1f} "
                    f"{ref_s / fast_s:6.1f}x"
                )
    if args.rollout_steps:
        print(
            f"\nVF episodes, {args.rollout_steps} steps of a batch of {args.batch} "
            "(ms per env step)"
        )
        print(f"{'objects':>7s} {'planner':>7s} {'fast ms':>9s} {'ref. ms':>9s} {'ratio':>7s}")
        for k in args.objects:
            for variant in args.variants:
                fast_s, ref_s = time_rollouts(k, variant, args)
                print(
                    f"{k:7d} {variant:>7s} {fast_s * 1e3:9.1f} {ref_s * 1e3:9.1f} "
                    f"{ref_s / fast_s:6.1f}x"
                )


if __name__ == "__main__":
    main()
