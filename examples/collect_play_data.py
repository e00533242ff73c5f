"""Collect random play data from a paper environment and save a picture of a few frames.

    python examples/collect_play_data.py --env rearrangement --num-objects 2 --out-dir outputs/demo

The buffer is written to ``<out-dir>/play_<env>`` (memory-mapped); a second run with the
same arguments loads it instead of collecting again.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from dorp_rl.data import FuturePairSampler, collect_play_data, future_pairs
from dorp_rl.envs import KeyCorridorEnv, KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.viz import save_frame_strip


def make_env(name: str, num_objects: int, num_envs: int):
    if name == "rearrangement":
        return ObjectRearrangementEnv(num_objects=num_objects, batch_size=(num_envs,))
    if name == "key-wall":
        return KeyWallEnv(batch_size=(num_envs,))
    if name == "key-corridor":
        return KeyCorridorEnv(batch_size=(num_envs,))
    raise ValueError(f"unknown env {name!r}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--env", default="rearrangement", choices=["rearrangement", "key-wall", "key-corridor"]
    )
    parser.add_argument("--num-objects", type=int, default=2)
    parser.add_argument("--num-frames", type=int, default=20_000)
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-dir", type=Path, default=Path("outputs/demo"))
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1: one per job)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    env = make_env(args.env, args.num_objects, args.num_envs)
    name = f"{args.env}-{args.num_objects}" if args.env == "rearrangement" else args.env
    buffer = collect_play_data(
        env,
        args.num_frames,
        directory=args.out_dir / f"play_{name}",
        seed=args.seed,
        sampler=FuturePairSampler(1, 1 if args.env == "rearrangement" else 4),
        batch_size=8,
        progress=True,
    )
    print(f"{len(buffer)} transitions in {args.out_dir / f'play_{name}'}")

    torch.manual_seed(args.seed)
    anchor, future, offset = future_pairs(buffer.sample())
    path = save_frame_strip(torch.stack([anchor, future]), args.out_dir / f"pairs_{name}.png")
    print(f"top row o_t, bottom row o_t+k (k = {offset.tolist()}): {path}")


if __name__ == "__main__":
    main()
