"""One DORP waypoint planning call through a latent world model against the true dynamics.

Both calls are a :class:`~dorp_rl.planners.RandomShootingPlanner` call of ``--candidates``
sequences of ``--planning-horizon`` steps for ``--rows`` acting envs, with DORP's
waypoint cost (:func:`~dorp_rl.policies.make_waypoint_cost`, the code term alone):

- ``true dynamics``: :class:`~dorp_rl.envs.GroundTruthModelEnv` of rearrangement, the
  cost encoding each distinct imagined frame with the representation preset's encoder
  (codes of frames seen in earlier calls kept, as the policy keeps them);
- ``latent model``: :class:`~dorp_rl.envs.LatentModelEnv` without frames, the cost
  reading the code head's codes (``("next", "code")``).

Latency does not depend on the weights, so both use freshly initialised models at the
given sizes (``--set FIELD=JSON`` for :class:`~dorp_rl.modules.LatentModelConfig`). Each
number is the median of ``--repeats`` calls after a warm-up call, the two alternating in
one process; the goal is a ratio of at most 5.

    python benchmarks/latent_planning_speed.py --objects 3 --threads 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from dorp_rl.envs import LatentModelEnv, ObjectRearrangementEnv
from dorp_rl.modules import DiscreteCodeEncoder, LatentModelConfig, LatentWorldModel
from dorp_rl.planners import RandomShootingPlanner
from dorp_rl.policies import make_planning_env, make_waypoint_cost
from dorp_rl.trainers import RepresentationConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=3)
    parser.add_argument("--rows", type=int, default=1, help="acting envs planned at once")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--planning-horizon", type=int, default=14)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--set", nargs="*", default=(), metavar="FIELD=JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    extra = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set)}
    env = ObjectRearrangementEnv(args.objects, batch_size=(args.rows,), seed=0)
    codes = RepresentationConfig.rearrangement(args.objects)
    encoder = DiscreteCodeEncoder(codes.encoder.replace(code_sizes=codes.code_sizes)).eval()
    model = LatentWorldModel(
        env.num_actions,
        LatentModelConfig(code_sizes=tuple(encoder.code_sizes), decoder=False, **extra),
    ).eval()
    td = env.reset()
    start = encoder(td["pixels"])[0]
    td.set("subgoal_code", start)
    td.set(
        "subgoal_mask",
        torch.zeros_like(start, dtype=torch.bool).index_fill_(-1, torch.tensor([0]), True),
    )
    shape = {"planning_horizon": args.planning_horizon, "num_candidates": args.candidates}
    planners = {
        "true dynamics": RandomShootingPlanner(
            make_planning_env(env, "gt"), make_waypoint_cost(encoder), seed=0, **shape
        ),
        "latent model": RandomShootingPlanner(
            LatentModelEnv(model),
            make_waypoint_cost(encoder, code_key=("next", "code")),
            seed=0,
            **shape,
        ),
    }
    times: dict[str, list[float]] = {name: [] for name in planners}
    for repeat in range(args.repeats + 1):
        for name, planner in planners.items():
            begin = time.perf_counter()
            planner.planning(td.clone())
            if repeat:  # the first call of each warms up
                times[name].append(time.perf_counter() - begin)
    medians = {name: statistics.median(values) for name, values in times.items()}
    out = {
        "objects": args.objects,
        "rows": args.rows,
        "candidates": args.candidates,
        "planning_horizon": args.planning_horizon,
        "threads": args.threads,
        "model": model.config.to_dict(),
        "median_ms": {name: round(1000 * value, 1) for name, value in medians.items()},
        "ratio": round(medians["latent model"] / medians["true dynamics"], 2),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
