"""One DORP waypoint planning call through a latent world model against the true dynamics.

Every call is a :class:`~dorp_rl.planners.RandomShootingPlanner` call of ``--candidates``
sequences of ``--planning-horizon`` steps for ``--rows`` acting envs, with DORP's
waypoint cost (:func:`~dorp_rl.policies.make_waypoint_cost`), in two forms:

- ``code term``: the code term alone. Through the true dynamics
  (:class:`~dorp_rl.envs.GroundTruthModelEnv` of rearrangement) the cost encodes each
  distinct imagined frame with the representation preset's encoder (codes of frames seen
  in earlier calls kept, as the policy keeps them); through the latent model
  (:class:`~dorp_rl.envs.LatentModelEnv` without frames) it reads the code head's codes.
- ``goal term``: as rearrangement's policy plans (its profile's DORP settings): the code
  term plus the goal image's blurred pixel distance, judged at the first arrival. Through
  the latent model every imagined frame is decoded, by the convolutional decoder and by
  the MLP one (``decoder_kind``); or, as the policy plans through a latent model, the
  goal term is the imagined latents' distance to the goal image's (``latent goal``), and
  nothing is decoded.
- ``goal phase``: the goal-image planner's cost (:func:`~dorp_rl.policies.make_goal_cost`
  as the policy builds it: blurred pixel distance, the encoder's object maps, the
  goal-code term), through the true dynamics and the latent model with the MLP decoder
  (whose frames the object-map term encodes).

The latent model imagines in ``--compute-dtype`` (``auto``, the planning env's default:
bfloat16 where the hardware runs it natively; ``float32``; ``bfloat16``).
Latency does not depend on the weights, so all use freshly initialised models at the
given sizes (``--set FIELD=JSON`` for :class:`~dorp_rl.modules.LatentModelConfig`). Each
number is the median of ``--repeats`` calls after a warm-up call, all alternating in one
process; the goal is a ratio of at most 5 to the true dynamics with the same cost.

    python benchmarks/latent_planning_speed.py --objects 3 --threads 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from dorp_rl.envs import LatentModelEnv, ObjectRearrangementEnv
from dorp_rl.envs.latent_planning import COMPUTE_DTYPES
from dorp_rl.modules import DiscreteCodeEncoder, LatentModelConfig, LatentWorldModel
from dorp_rl.planners import RandomShootingPlanner
from dorp_rl.policies import DORPConfig, make_planning_env, make_waypoint_cost
from dorp_rl.policies.factory import make_goal_cost
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
    parser.add_argument("--compute-dtype", default="auto", choices=COMPUTE_DTYPES)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    extra = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set)}
    env = ObjectRearrangementEnv(args.objects, batch_size=(args.rows,), seed=0)
    codes = RepresentationConfig.for_env("rearrangement", args.objects)
    encoder = DiscreteCodeEncoder(codes.encoder.replace(code_sizes=codes.code_sizes)).eval()

    def model(**fields) -> LatentWorldModel:
        config = LatentModelConfig(code_sizes=tuple(encoder.code_sizes), **{**extra, **fields})
        return LatentWorldModel(env.num_actions, config).eval()

    def latent_env(planned: LatentWorldModel, decode: bool = False) -> LatentModelEnv:
        return LatentModelEnv(planned, decode=decode, compute_dtype=args.compute_dtype)

    td = env.reset()
    start = encoder(td["pixels"])[0]
    td.set("subgoal_code", start)
    td.set(
        "subgoal_mask",
        torch.zeros_like(start, dtype=torch.bool).index_fill_(-1, torch.tensor([0]), True),
    )
    shape = {"planning_horizon": args.planning_horizon, "num_candidates": args.candidates}
    dorp = DORPConfig.for_env("rearrangement", num_objects=args.objects)
    goal_term = {
        "waypoint_goal_weight": dorp.waypoint_goal_weight,
        "step_penalty": dorp.waypoint_step_penalty,
        "first_arrival": dorp.waypoint_first_arrival,
        "goal_blur_sigmas": dorp.goal_blur_sigmas,
    }
    gt = make_planning_env(env, "gt")
    predicted = {"code_key": ("next", "code")}
    planners = {
        "code term, true dynamics": (gt, make_waypoint_cost(encoder)),
        "code term, latent model": (
            latent_env(model(decoder=False)),
            make_waypoint_cost(encoder, **predicted),
        ),
        "goal term, true dynamics": (gt, make_waypoint_cost(encoder, **goal_term)),
        "goal term, latent model, conv decoder": (
            latent_env(model(decoder_kind="conv"), decode=True),
            make_waypoint_cost(encoder, **goal_term, **predicted),
        ),
        "goal term, latent model, mlp decoder": (
            latent_env(model(decoder_kind="mlp"), decode=True),
            make_waypoint_cost(encoder, **goal_term, **predicted),
        ),
    }
    judged = latent_env(model(decoder_kind="mlp"))
    planners["goal term, latent model, latent goal"] = (
        judged,
        make_waypoint_cost(encoder, **goal_term, **predicted, latent_model=judged.latent_model),
    )
    goal_phase = {
        "goal_code_weight": dorp.goal_code_weight,
        "goal_blur_sigmas": dorp.goal_blur_sigmas,
        "goal_map_weight": DORPConfig.WHERE_SUITED["goal_map_weight"],
    }
    td.set("goal_code", start)
    td.set("goal_code_weight", torch.full((args.rows, 1), dorp.goal_code_weight))
    planners["goal phase, true dynamics"] = (gt, make_goal_cost(encoder, **goal_phase))
    planners["goal phase, latent model, mlp decoder"] = (
        latent_env(model(decoder_kind="mlp"), decode=True),
        make_goal_cost(encoder, **goal_phase, **predicted),
    )
    planners = {
        name: RandomShootingPlanner(planning_env, cost, seed=0, **shape)
        for name, (planning_env, cost) in planners.items()
    }
    times: dict[str, list[float]] = {name: [] for name in planners}
    for repeat in range(args.repeats + 1):
        for name, planner in planners.items():
            begin = time.perf_counter()
            planner.planning(td.clone())
            if repeat:  # the first call of each warms up
                times[name].append(time.perf_counter() - begin)
    medians = {name: statistics.median(values) for name, values in times.items()}
    reference = {
        kind: f"{kind}, true dynamics" for kind in ("code term", "goal term", "goal phase")
    }
    out = {
        "objects": args.objects,
        "rows": args.rows,
        "candidates": args.candidates,
        "planning_horizon": args.planning_horizon,
        "threads": args.threads,
        "step_dtype": str(judged.step_dtype).removeprefix("torch."),
        "model": LatentModelConfig(code_sizes=tuple(encoder.code_sizes), **extra).to_dict(),
        "median_ms": {name: round(1000 * value, 1) for name, value in medians.items()},
        "ratio": {
            name: round(value / medians[reference[name.split(",")[0]]], 2)
            for name, value in medians.items()
            if "latent" in name
        },
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
