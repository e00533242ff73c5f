"""The latent world model's training cost per frame size, as a ratio to 16 x 16 frames.

One step of the recipe's model (:meth:`~dorp_rl.modules.LatentModelConfig.recipe`, its
``frame_stride`` chosen from the frame size): encode 32 frames, 14 imagined steps each decoded to a frame, a loss on the decoded frames,
backward and an Adam step; random uint8 frames of 16, 32, 64 and 84 pixels a side, timed
interleaved (median of ``--repeats`` rounds after one untimed round) in one process::

    .venv/bin/python benchmarks/latent_training_speed.py --threads 1
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch

from dorp_rl.modules.latent import LatentModelConfig, LatentWorldModel


def make_step(size: int, batch: int, horizon: int, actions: int = 8) -> Callable[[], None]:
    """One training-like step of the recipe's model on ``[batch, 3, size, size]`` frames."""
    config = LatentModelConfig.recipe(frame_shape=(3, size, size), code_sizes=(32, 32))
    model = LatentWorldModel(actions, config)
    optimizer = torch.optim.Adam(model.parameters(), 1e-3)
    pixels = torch.randint(0, 256, (batch, 3, size, size), dtype=torch.uint8)
    action = torch.randint(0, actions, (batch, horizon))

    def step() -> None:
        latent = model.encode(pixels)
        loss = torch.zeros(())
        for t in range(horizon):
            latent = model.step(latent, action[:, t])
            loss = loss + model.decode(latent).float().square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64, 84])
    parser.add_argument("--batch", type=int, default=32, help="windows per step")
    parser.add_argument("--horizon", type=int, default=14, help="imagined steps per window")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: one per job)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    sizes = sorted({16, *args.sizes})
    steps = {n: make_step(n, args.batch, args.horizon) for n in sizes}
    times: dict[int, list[float]] = {n: [] for n in sizes}
    for round_ in range(args.repeats + 1):
        for n in sizes:
            start = time.perf_counter()
            steps[n]()
            if round_:  # the first round warms up
                times[n].append(time.perf_counter() - start)
    base = statistics.median(times[16])
    print("| frames | ms per step | ratio to 16 x 16 |\n|---|---|---|")
    for n in sizes:
        median = statistics.median(times[n])
        print(f"| 3 x {n} x {n} | {median * 1000:.0f} | {median / base:.1f}x |")


if __name__ == "__main__":
    main()
