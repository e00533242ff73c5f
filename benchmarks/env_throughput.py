"""Frames per second of the dorp-rl environments, as a ratio to Farama MiniGrid.

What is measured
----------------
For every environment (``ObjectRearrangementEnv`` with 1, 3 and 6 objects, ``KeyWallEnv``,
``KeyCorridorEnv``) at batch sizes 1, 64 and 1024 (``batch_size=(B,)``), on CPU:

- ``step``: a hand-written loop ``td["action"] = a[t]; td = env.step(td)["next"]``. It
  goes through TorchRL's public ``EnvBase.step`` (spec checks, ``"next"`` nesting) but
  never resets: it is the cost of the simulator plus the thinnest TorchRL wrapper.
- ``rollout``: ``env.rollout(n, actions=a, break_when_any_done=False)``, i.e. TorchRL's
  own loop with ``step_and_maybe_reset`` (done checks and partial auto-resets) and the
  per-step tensordicts it keeps and stacks. As in a collector, consecutive calls of at
  most ``ROLLOUT_CHUNK`` steps carry on from where the previous one ended
  (``auto_reset=False, tensordict=last["next"]``), so the full reset that a fresh
  ``rollout`` starts with is paid once, not once per call.
- ``_step`` (optional, ``--modes _step``): the bare ``env._step(td)`` without TorchRL's
  wrapper, to see how much of ``step`` is framework overhead.

A frame is one transition of one batch element, so a step of a batch of 1024 counts
1024 frames. Actions are uniformly random and drawn up front as one tensor, so that no
policy cost is timed. Every step renders the 16x16 RGB ``pixels`` observation.

The baseline is ``gymnasium.make("MiniGrid-DoorKey-16x16-v0")`` (PyPI ``minigrid``):
a single, unbatched env stepped with pre-drawn random actions from its action space and
reset whenever ``terminated`` or ``truncated`` is set (gymnasium's default wrappers
included, no ``render_mode``).

Why a ratio
-----------
Benchmarks run on shared, noisy machines where absolute frames/s move by tens of
percent from one run to the next. MiniGrid is therefore measured in the same process,
in short bursts interleaved with ours (one before the first configuration, then one
after every environment and batch size), and every result is reported as a ratio to
the median of all those samples; their range is printed as a measure of the noise. The project's goal is that every environment reaches at least
100x MiniGrid's single-env frames/s at batch 1024.

Each number is the median of several timed repeats (``time.perf_counter``; 5, or 3
with ``--quick``) after a warm-up; the number of steps in a repeat is calibrated during
the warm-up so that a repeat lasts about 0.2 s (0.05 s with ``--quick``). Torch keeps
its default thread count unless ``--threads`` is given.

Usage::

    .venv/bin/python benchmarks/env_throughput.py            # full run, about a minute
    .venv/bin/python benchmarks/env_throughput.py --quick    # a few seconds
    .venv/bin/python benchmarks/env_throughput.py --json results.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from importlib.metadata import version
from pathlib import Path

import gymnasium
import minigrid  # noqa: F401  (registers the MiniGrid-* ids)
import numpy as np
import torch
from tensordict import TensorDictBase

from dorp_rl.envs import GridWorldEnv, KeyCorridorEnv, KeyWallEnv, ObjectRearrangementEnv

MINIGRID_ID = "MiniGrid-DoorKey-16x16-v0"
GOAL_BATCH = 1024
GOAL_RATIO = 100.0
ALL_MODES = ("step", "rollout", "_step")
DEFAULT_MODES = ("step", "rollout")
DEFAULT_BATCHES = (1, 64, 1024)
#: Most steps of one ``rollout`` call (it keeps every step in memory until it returns).
ROLLOUT_CHUNK = 32
#: Pre-drawn actions per ``rollout`` call cycle through this many chunks.
ROLLOUT_ACTION_POOL = 4

ENV_FACTORIES: dict[str, Callable[..., GridWorldEnv]] = {
    "ObjectRearrangement(k=1)": lambda **kw: ObjectRearrangementEnv(num_objects=1, **kw),
    "ObjectRearrangement(k=3)": lambda **kw: ObjectRearrangementEnv(num_objects=3, **kw),
    "ObjectRearrangement(k=6)": lambda **kw: ObjectRearrangementEnv(num_objects=6, **kw),
    "KeyWall": lambda **kw: KeyWallEnv(**kw),
    "KeyCorridor": lambda **kw: KeyCorridorEnv(**kw),
}


@dataclass
class Settings:
    """How long and how often each configuration is timed."""

    repeat_seconds: float
    repeats: int
    warmup_seconds: float
    minigrid_burst_repeats: int
    #: Repeats when a single step already takes more than two repeat times.
    slow_repeats: int = 3


@dataclass
class Result:
    """Throughput of one (environment, batch, mode) configuration."""

    env: str
    batch: int
    mode: str
    fps: float
    fps_samples: list[float]
    ratio: float = float("nan")


@dataclass
class Baseline:
    """MiniGrid single-env frames/s samples collected over the run."""

    samples: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        return statistics.median(self.samples)


# ---------------------------------------------------------------------- #
# Timing helpers
# ---------------------------------------------------------------------- #
def _calibrate(
    run: Callable[[int], int], warmup_seconds: float, repeat_seconds: float
) -> tuple[int, float]:
    """Warms ``run`` up; returns how many units make a repeat, and the seconds of one unit.

    ``run(n)`` performs ``n`` units of work (steps or rollouts) and returns the frames done.
    At least one call is made, so a unit slower than the warm-up is still warmed up once.
    """
    n = 1
    rate = 0.0  # units per second of the last call
    spent = 0.0
    while spent < warmup_seconds:
        start = time.perf_counter()
        run(n)
        elapsed = time.perf_counter() - start
        spent += elapsed
        rate = n / max(elapsed, 1e-9)
        if elapsed < warmup_seconds / 4:
            n *= 2
    return max(1, round(rate * repeat_seconds)), 1.0 / rate


def _time_repeats(run: Callable[[int], int], n: int, repeats: int) -> list[float]:
    """Frames/s of ``repeats`` timed calls of ``run(n)``."""
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        frames = run(n)
        samples.append(frames / (time.perf_counter() - start))
    return samples


# ---------------------------------------------------------------------- #
# MiniGrid baseline
# ---------------------------------------------------------------------- #
class MiniGridRunner:
    """Steps one ``MiniGrid-DoorKey-16x16-v0`` with pre-drawn random actions."""

    def __init__(self, seed: int) -> None:
        self.env = gymnasium.make(MINIGRID_ID)
        self.env.reset(seed=seed)
        self.env.action_space.seed(seed)
        num_actions = int(self.env.action_space.n)
        self.actions = self.env.action_space.np_random.integers(num_actions, size=1 << 16)
        self.cursor = 0

    def run(self, n: int) -> int:
        env, actions = self.env, self.actions
        size = len(actions)
        cursor = self.cursor
        for _ in range(n):
            _, _, terminated, truncated, _ = env.step(int(actions[cursor]))
            cursor = (cursor + 1) % size
            if terminated or truncated:
                env.reset()
        self.cursor = cursor
        return n

    def burst(self, settings: Settings, repeats: int) -> list[float]:
        n, _ = _calibrate(self.run, settings.warmup_seconds / 2, settings.repeat_seconds)
        return _time_repeats(self.run, n, repeats)


# ---------------------------------------------------------------------- #
# dorp-rl environments
# ---------------------------------------------------------------------- #
def _step_runner(env: GridWorldEnv, batch: int, mode: str, seed: int) -> Callable[[int], int]:
    """A ``run(n)`` doing ``n`` steps of ``env`` through ``env.step`` or ``env._step``."""
    generator = torch.Generator().manual_seed(seed)
    num_actions = env.num_actions
    state: dict[str, TensorDictBase | torch.Tensor] = {"td": env.reset()}
    cache: dict[int, torch.Tensor] = {}

    def actions_for(n: int) -> torch.Tensor:
        if n not in cache:
            cache.clear()
            cache[n] = torch.randint(num_actions, (n, batch, 1), generator=generator)
        return cache[n]

    def run(n: int) -> int:
        actions = actions_for(n)
        td = state["td"]
        if mode == "step":
            for t in range(n):
                td["action"] = actions[t]
                td = env.step(td)["next"]
        else:
            for t in range(n):
                td["action"] = actions[t]
                td = env._step(td)
        state["td"] = td
        return n * batch

    return run


def _rollout_runner(env: GridWorldEnv, batch: int, seed: int) -> Callable[[int], int]:
    """A ``run(n)`` doing ``n`` steps through ``env.rollout`` calls of at most
    :data:`ROLLOUT_CHUNK` steps, each carrying on from where the previous one ended."""
    generator = torch.Generator().manual_seed(seed)
    pool = torch.randint(
        env.num_actions, (ROLLOUT_ACTION_POOL, ROLLOUT_CHUNK, batch, 1), generator=generator
    )
    carry: dict[str, TensorDictBase | None] = {"td": None}
    calls = [0]

    def run(n: int) -> int:
        remaining = n
        while remaining > 0:
            length = min(remaining, ROLLOUT_CHUNK)
            actions = pool[calls[0] % ROLLOUT_ACTION_POOL, :length]
            calls[0] += 1
            td = carry["td"]
            out = env.rollout(
                length,
                actions=actions,
                break_when_any_done=False,
                auto_reset=td is None,
                tensordict=td,
            )
            carry["td"] = out[..., -1]["next"]
            remaining -= length
        return n * batch

    return run


def bench_env(
    name: str, batch: int, modes: Sequence[str], settings: Settings, seed: int
) -> list[Result]:
    """Times every mode of one environment at one batch size."""
    results = []
    env = ENV_FACTORIES[name](batch_size=(batch,), seed=seed)
    for mode in modes:
        if mode == "rollout":
            run = _rollout_runner(env, batch, seed)
        else:
            run = _step_runner(env, batch, mode, seed)
        n, unit_seconds = _calibrate(run, settings.warmup_seconds, settings.repeat_seconds)
        repeats = settings.repeats
        if unit_seconds > 2 * settings.repeat_seconds:
            repeats = min(repeats, settings.slow_repeats)
        samples = _time_repeats(run, n, repeats)
        results.append(Result(name, batch, mode, statistics.median(samples), samples))
        print(f"  {name:<26} B={batch:<5} {mode:<8} {results[-1].fps:>13,.0f} frames/s")
    return results


# ---------------------------------------------------------------------- #
# Report
# ---------------------------------------------------------------------- #
def print_report(results: list[Result], baseline: Baseline, modes: Sequence[str]) -> None:
    spread = f"{min(baseline.samples):,.0f} .. {max(baseline.samples):,.0f}"
    print()
    print(
        f"MiniGrid {MINIGRID_ID}, single env: {baseline.median:,.0f} frames/s "
        f"(median of {len(baseline.samples)} samples, range {spread})"
    )
    print(f"torch threads: {torch.get_num_threads()}")
    print(f"rollout: calls of <= {ROLLOUT_CHUNK} steps, each continuing the previous one")
    print()
    header = f"{'env':<26} {'batch':>6} {'mode':<8} {'frames/s':>13} {'vs MiniGrid':>12}"
    print(header)
    print("-" * len(header))
    last_env = None
    for r in results:
        if last_env is not None and r.env != last_env:
            print()
        last_env = r.env
        print(f"{r.env:<26} {r.batch:>6} {r.mode:<8} {r.fps:>13,.0f} {r.ratio:>11.1f}x")
    print()
    goal_rows = [r for r in results if r.batch == GOAL_BATCH]
    if not goal_rows:
        print(f"Goal (>= {GOAL_RATIO:.0f}x MiniGrid at batch {GOAL_BATCH}): batch not measured.")
        return
    print(f"Goal: >= {GOAL_RATIO:.0f}x MiniGrid single-env frames/s at batch {GOAL_BATCH}")
    for name in dict.fromkeys(r.env for r in goal_rows):
        parts = []
        for mode in modes:
            row = next((r for r in goal_rows if r.env == name and r.mode == mode), None)
            if row is not None:
                verdict = "met" if row.ratio >= GOAL_RATIO else "NOT met"
                parts.append(f"{mode} {row.ratio:.1f}x {verdict}")
        print(f"  {name:<26} " + ", ".join(parts))


def write_json(
    path: Path, results: list[Result], baseline: Baseline, settings: Settings, quick: bool
) -> None:
    payload = {
        "minigrid": {
            "env_id": MINIGRID_ID,
            "fps_median": baseline.median,
            "fps_samples": baseline.samples,
        },
        "goal": {"batch": GOAL_BATCH, "ratio": GOAL_RATIO},
        "results": [asdict(r) for r in results],
        "settings": {**asdict(settings), "quick": quick},
        "system": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "torchrl": version("torchrl"),
            "tensordict": version("tensordict"),
            "gymnasium": gymnasium.__version__,
            "minigrid": version("minigrid"),
            "numpy": np.__version__,
            "torch_threads": torch.get_num_threads(),
        },
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"\nwrote {path}")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Frames/s of the dorp-rl envs at several batch sizes, as a ratio to "
        f"MiniGrid's {MINIGRID_ID} stepped in the same run."
    )
    parser.add_argument("--quick", action="store_true", help="short repeats (a few seconds).")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH", help="write JSON.")
    parser.add_argument(
        "--batches", type=int, nargs="+", default=list(DEFAULT_BATCHES), metavar="B"
    )
    parser.add_argument(
        "--modes", nargs="+", choices=ALL_MODES, default=list(DEFAULT_MODES), metavar="MODE"
    )
    parser.add_argument(
        "--envs", nargs="+", choices=list(ENV_FACTORIES), default=list(ENV_FACTORIES)
    )
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (median).")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch.set_num_threads(N) before timing (default 1: one per job; on a shared "
        "2-core CPU more made steps far slower).",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> list[Result]:
    args = parse_args(argv)
    if args.quick:
        settings = Settings(
            repeat_seconds=0.05,
            repeats=3,
            warmup_seconds=0.05,
            minigrid_burst_repeats=2,
        )
    else:
        settings = Settings(
            repeat_seconds=0.2,
            repeats=5,
            warmup_seconds=0.15,
            minigrid_burst_repeats=2,
        )
    if args.repeats is not None:
        settings.repeats = max(1, args.repeats)

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    minigrid_runner = MiniGridRunner(args.seed)
    baseline = Baseline()
    results: list[Result] = []

    def minigrid_burst() -> None:
        samples = minigrid_runner.burst(settings, settings.minigrid_burst_repeats)
        baseline.samples.extend(samples)
        print(
            f"  {'MiniGrid (1 env)':<26} {'':<7} {'':<8} {statistics.median(samples):>13,.0f} frames/s"
        )

    print(f"timing (torch threads: {torch.get_num_threads()}, quick: {args.quick})")
    minigrid_burst()
    for name in args.envs:
        for batch in args.batches:
            results.extend(bench_env(name, batch, args.modes, settings, args.seed))
            minigrid_burst()

    for r in results:
        r.ratio = r.fps / baseline.median
    print_report(results, baseline, args.modes)
    if args.json is not None:
        write_json(args.json, results, baseline, settings, args.quick)
    return results


if __name__ == "__main__":
    main()
