"""Code-training steps per second at several frame sizes, with and without a map stride.

What is measured
----------------
One training step of DORP's codes as :class:`~dorp_rl.trainers.RepresentationTrainer`
takes it: :class:`~dorp_rl.objectives.CPCLoss` (DDDP similarity, with the exclusivity,
sparsity and motion terms of the presets, ``--plain`` drops them) on a batch of
``--batch`` pairs (twice as many frames through the encoder), the sum of its ``loss_*``
terms backpropagated and one Adam step of encoder and similarity. Frames are random
uint8, ``--channels`` x N x N for each N of ``--sizes``, and the encoder is
:meth:`~dorp_rl.modules.EncoderConfig.small` with ``--code-sizes``.

Each frame size runs with the map stride :func:`~dorp_rl.modules.choose_map_stride`
picks (``map_stride`` column) and, for comparison, with ``map_stride=1`` (every pixel,
the encoder before map strides). All settings are timed interleaved, one step each per
round, and every figure is the median over ``--repeats`` rounds after a warm-up, printed
as a ratio to the 16 x 16 step of the same run (the goal: within 3x at 64 x 64 and
84 x 84 with the chosen stride).

Usage::

    .venv/bin/python benchmarks/code_training_speed.py --threads 1
    .venv/bin/python benchmarks/code_training_speed.py --sizes 16 64 --repeats 3 --quick
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
from bench_threads import add_threads_argument, parse_with_threads
from tensordict import TensorDict

from dorp_rl.modules import (
    DDDPSimilarity,
    DiscreteCodeEncoder,
    EncoderConfig,
    choose_map_stride,
)
from dorp_rl.objectives import CPCLoss


def make_step(
    frame_shape: tuple[int, int, int],
    map_stride: int,
    code_sizes: tuple[int, ...],
    batch: int,
    plain: bool,
    seed: int,
) -> Callable[[], float]:
    """A function doing one training step on fixed random pairs; returns the loss."""
    torch.manual_seed(seed)
    config = EncoderConfig.small(code_sizes, frame_shape=frame_shape, map_stride=map_stride)
    encoder = DiscreteCodeEncoder(config)
    similarity = DDDPSimilarity(encoder.num_onehots * encoder.max_codes)
    weights = {} if plain else {"exclusivity_weight": 3.0, "sparsity_weight": 5.0}
    if not plain:
        weights["motion_weight"] = 1.0
    loss = CPCLoss(encoder, similarity, **weights)
    optimizer = torch.optim.Adam([*encoder.parameters(), *similarity.parameters()], lr=1e-3)
    pixels = torch.randint(0, 256, (batch, *frame_shape), dtype=torch.uint8)
    future = torch.randint(0, 256, (batch, *frame_shape), dtype=torch.uint8)
    td = TensorDict(pixels=pixels, future_pixels=future, batch_size=[batch])

    def step() -> float:
        out = loss(td)
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()
        return float(total.detach())

    return step


def timed(fn: Callable[[], float]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[16, 32, 64, 84])
    parser.add_argument("--channels", type=int, default=3)
    parser.add_argument("--code-sizes", type=int, nargs="+", default=[32, 32])
    parser.add_argument("--batch", type=int, default=128, help="pairs per step")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds")
    parser.add_argument("--warmup", type=int, default=2, help="untimed rounds first")
    parser.add_argument("--plain", action="store_true", help="CPC term only, no map terms")
    parser.add_argument(
        "--quick", action="store_true", help="skip map_stride=1 above 32 x 32 (the slow steps)"
    )
    parser.add_argument("--seed", type=int, default=0)
    add_threads_argument(parser)
    args = parse_with_threads(parser)
    if 16 not in args.sizes:
        args.sizes = [16, *args.sizes]

    settings: dict[tuple[int, int], Callable[[], float]] = {}
    for size in args.sizes:
        shape = (args.channels, size, size)
        strides = {choose_map_stride(shape)}
        if not (args.quick and size > 32):
            strides.add(1)
        for stride in sorted(strides):
            settings[size, stride] = make_step(
                shape, stride, tuple(args.code_sizes), args.batch, args.plain, args.seed
            )
    times: dict[tuple[int, int], list[float]] = {key: [] for key in settings}
    for _ in range(args.warmup):
        for step in settings.values():
            step()
    for _ in range(args.repeats):
        for key, step in settings.items():
            times[key].append(timed(step))
    median = {key: statistics.median(values) for key, values in times.items()}
    base = median[16, 1]

    terms = "CPC only" if args.plain else "CPC + exclusivity + sparsity + motion"
    print(
        f"One code-training step: {args.batch} pairs ({2 * args.batch} frames), "
        f"code sizes {tuple(args.code_sizes)}, {terms}, {args.threads} torch thread(s), "
        f"median of {args.repeats} interleaved rounds; ratio = time / time at 16 x 16.\n"
    )
    print(
        "| frames | map_stride | map cells | ms/step | steps/s | ratio to 16x16 "
        "| map_stride=1 ms/step | map_stride=1 ratio |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        shape = (args.channels, size, size)
        stride = choose_map_stride(shape)
        cells = -(-size // stride)
        seconds = median[size, stride]
        plain = median.get((size, 1))
        plain_cols = f"{plain * 1e3:.0f} | {plain / base:.1f}x" if plain is not None else "- | -"
        print(
            f"| {args.channels}x{size}x{size} | {stride} | {cells}x{cells} | {seconds * 1e3:.0f} "
            f"| {1 / seconds:.2f} | {seconds / base:.2f}x | {plain_cols} |"
        )


if __name__ == "__main__":
    main()
