"""Learn DORP's discrete codes and draw their code maps (the paper's Figures 5 and 6).

    python examples/train_representation.py --steps 800 --out-dir outputs/representation_1obj
    python examples/train_representation.py --env key-wall --out-dir outputs/representation_keywall

Prints the ground-truth diagnostics (codes used, connectivity; for key rooms whether the
key bit and the agent one-hot are separate) and writes the pictures under
``<out-dir>/plots``. Key-wall takes about 4 minutes on a 2-core CPU (3000 steps).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer
from dorp_rl.viz import write_diagnostic_plots


def make_config(args: argparse.Namespace) -> RepresentationConfig:
    common = {"seed": args.seed, "out_dir": str(args.out_dir)}
    if args.env == "rearrangement":
        config = RepresentationConfig.for_env(
            "rearrangement",
            args.num_objects,
            similarity=args.similarity,
            num_steps=args.steps or 800,
            num_frames=50_000,
            **common,
        )
    elif args.env == "key-wall":
        config = RepresentationConfig.for_env("key-wall", similarity=args.similarity, **common)
    else:
        config = RepresentationConfig.for_env("key-corridor", similarity=args.similarity, **common)
    if args.steps:
        config.num_steps = args.steps
        config.candidate_steps = min(config.candidate_steps, args.steps)
    if args.candidates:
        config.num_candidates = args.candidates
    config.diagnostics_every = max(config.num_steps // 4, 1)
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--env", default="rearrangement", choices=["rearrangement", "key-wall", "key-corridor"]
    )
    parser.add_argument("--num-objects", type=int, default=1, help="rearrangement only")
    parser.add_argument("--similarity", default="dddp", choices=["dddp", "full", "identity"])
    parser.add_argument("--steps", type=int, default=None, help="default: 800, or the preset's")
    parser.add_argument(
        "--candidates",
        type=int,
        default=None,
        help="screen this many initialisations by label-free code information first (default 1)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", type=Path, default=Path("outputs/representation_1obj"))
    parser.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1: one per job)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    trainer = RepresentationTrainer(make_config(args))
    result = trainer.train(resume=args.resume)
    diag = result["diagnostics"]
    print(
        f"steps {result['step']}, restarts {len(result['restarts'])}, collapsed {result['collapsed']}"
    )
    if result["candidates"]:
        scores = ", ".join(f"{c['score']:.2f}" for c in result["candidates"])
        chosen = result["chosen_candidate"]["attempt"]
        print(f"candidate code information (nats): {scores}; continued candidate {chosen}")
    if args.env == "rearrangement":
        print(f"codes used per one-hot: {diag['codes_used']}")
        print(f"selectivity {diag['selectivity']:.3f}, purity {diag['purity']}")
        print(f"connected codes: {diag['connected_fraction']}")
    else:
        print(
            f"key bit changes on {diag['key_bit_change_fraction']:.3f} of key events; "
            f"agent one-hot unchanged on {diag['agent_onehot_unchanged_fraction']:.3f}"
        )
        print(
            f"agent codes used: {diag['codes_used']}, connected without / with key: "
            f"{diag['connected_fraction_without_key']:.2f} / {diag['connected_fraction_with_key']:.2f}"
        )
    paths = write_diagnostic_plots(trainer.env, trainer.encoder.encode, args.out_dir / "plots")
    for name, path in paths.items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    main()
