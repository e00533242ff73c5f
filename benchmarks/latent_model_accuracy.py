"""Trains a latent world model and prints its open-loop code accuracy and wall-clock.

The goal: over 14 open-loop steps on held-out play data (another seed), the code head's
codes equal the DORP encoder's codes of the true frames on >= 95% of the steps, at 1, 2,
3 and 5 objects and in both key rooms, with the decoded frames' pixel accuracy beside it;
training within 10 minutes at one torch thread at 3 objects.

The codes are those of a representation checkpoint (``--codes PATH``) or oracle codes of
the true positions (``--codes oracle``, regions of ``--cell-size`` cells: a quick stand-in
while trying architectures). ``--set FIELD=JSON`` changes fields of
:class:`~dorp_rl.trainers.LatentWorldModelConfig` (``model='{"latent_dim": 256}'``).
``--resume`` goes on from the last checkpoint of ``--out-dir`` to ``--steps`` steps (the
same other arguments).

    python benchmarks/latent_model_accuracy.py --env rearrangement --num-objects 3 \\
        --codes oracle --steps 2000 --json outputs/latent/k3.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from dorp_rl.envs import OracleCodeEncoder
from dorp_rl.trainers import LatentWorldModelConfig, LatentWorldModelTrainer, load_encoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="rearrangement", help="env profile")
    parser.add_argument("--num-objects", type=int, default=None)
    parser.add_argument("--codes", default="oracle", help="'oracle' or a representation checkpoint")
    parser.add_argument("--cell-size", type=int, default=4, help="oracle codes: cells per region")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=64_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out-dir", default="outputs/latent_model")
    parser.add_argument("--json", default=None, help="write the result here too")
    parser.add_argument("--set", nargs="*", default=(), metavar="FIELD=JSON")
    parser.add_argument(
        "--eval-every", type=int, default=None, help="steps between evaluations (steps // 4)"
    )
    parser.add_argument(
        "--eval-windows",
        type=int,
        default=4096,
        help="held-out windows the accuracy is measured on (on 512, the figure over 14 "
        "steps moves by about 0.01 between draws)",
    )
    parser.add_argument(
        "--eval-frames", type=int, default=64_000, help="held-out play transitions they come from"
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="go on from the last checkpoint in --out-dir up to --steps (the same other "
        "settings, --eval-every included)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    extra = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.set)}
    cfg = LatentWorldModelConfig.for_env(
        args.env,
        args.num_objects,
        num_steps=args.steps,
        num_frames=args.frames,
        seed=args.seed,
        eval_every=args.eval_every or max(args.steps // 4, 1),
        eval_sequences=args.eval_windows,
        eval_frames=args.eval_frames,
        out_dir=args.out_dir,
        progress=False,
        **extra,
    )
    env = cfg.make_env(batch_size=(4,))
    if args.codes == "oracle":
        encoder = OracleCodeEncoder(env, cell_size=args.cell_size)
    else:
        encoder = load_encoder(args.codes, env)
    start = time.perf_counter()
    trainer = LatentWorldModelTrainer(cfg, encoder=encoder)
    result = trainer.train(resume=args.resume)
    seconds = time.perf_counter() - start
    evaluation = result["evaluation"]
    pixels = evaluation["pixel_accuracy"]
    out = {
        "env": args.env,
        "num_objects": cfg.num_objects,
        "codes": args.codes,
        "code_sizes": list(encoder.code_sizes),
        "steps": args.steps,
        "set": extra,
        "train_seconds": round(seconds, 1),  # of this run only, when resumed
        "resumed_from_step": result.get("resumed_from_step"),
        "code_accuracy": [round(x, 4) for x in evaluation["code_accuracy"]],
        "code_accuracy_all_steps": round(sum(evaluation["code_accuracy"]) / cfg.horizon, 4),
        "pixel_accuracy": None if pixels is None else [round(x, 4) for x in pixels],
        "num_sequences": evaluation["num_sequences"],
        # windows holding a rare code change (the key taken), drawn when event_share > 0
        "event_num_sequences": evaluation.get("event_num_sequences"),
        "event_code_accuracy": {
            k.removeprefix("event_code_accuracy_"): round(v, 4)
            for k, v in evaluation.items()
            if k.startswith("event_code_accuracy_step")
        },
    }
    print(json.dumps(out))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
