"""Planning through a gymnasium env's own dynamics: GymGoalEnv against stepping MiniGrid.

What is measured
----------------
One waypoint-sized planning call (``--candidates`` x ``--horizon`` random action
sequences for each of ``--batch`` acting rows, as a random-shooting planner imagines them)
through :class:`~dorp_rl.envs.GymGoalEnv` over MiniGrid DoorKey 5x5 (the example's
``examples/gymnasium_env.py``), against the cost of stepping and rendering MiniGrid
itself measured in the same run:

- ``minigrid``: seconds per ``step`` + ``render`` of the gymnasium env (``--probe``
  calls), and what one planning call would cost if every imagined step were one;
- ``cold``: the first planning call of a fresh env (its tables filled on the way);
- ``warm``: later calls from other states (median of ``--repeats``), each from a row of
  reachable states: what a policy pays once the dynamics have been seen.

Printed: seconds per call, MiniGrid calls made, and the ratios to the all-MiniGrid
estimate.

Usage::

    .venv/bin/python benchmarks/gym_goal_planning.py
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

import gymnasium_env as door_key  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=14)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--probe", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    gym_env = door_key.make_door_key_gym()
    gym_env.reset()
    start = time.perf_counter()
    for i in range(args.probe):
        gym_env.step(i % 5)
        gym_env.render()
    per_call = (time.perf_counter() - start) / args.probe
    imagined = args.batch * args.candidates * args.horizon
    print(f"MiniGrid step + render: {per_call * 1e3:.3f} ms ({1 / per_call:.0f} per s)")
    print(f"one planning call, every imagined step in MiniGrid: {imagined * per_call:.2f} s")

    model = door_key.make_env(batch_size=(), seed=0)
    states = model.reachable_states()
    g = torch.Generator().manual_seed(0)

    def call(rows: list[tuple]) -> float:
        state = torch.tensor(rows).unsqueeze(1).expand(-1, args.candidates, -1)
        actions = torch.randint(0, 5, (len(rows), args.candidates, args.horizon), generator=g)
        begin = time.perf_counter()
        for t in range(args.horizon):
            state = model.transition(state, actions[..., t])
            model.render_states(state)
        return time.perf_counter() - begin

    def pick() -> list[tuple]:
        return [states[int(i)] for i in torch.randint(0, len(states), (args.batch,), generator=g)]

    fresh = door_key.make_env(batch_size=(), seed=0)
    model, warm_model = fresh, model
    before = fresh.dynamics.gym_calls
    cold = call(pick())
    print(
        f"cold call: {cold:.2f} s, MiniGrid calls {fresh.dynamics.gym_calls - before} "
        f"(reachable states {len(states)})"
    )
    model = warm_model
    call(pick())
    warm = statistics.median(call(pick()) for _ in range(args.repeats))
    print(
        f"warm call: {warm:.3f} s, {args.batch}x{args.candidates}x{args.horizon} imagined steps; "
        f"all-MiniGrid estimate / warm = {imagined * per_call / warm:.1f}x, "
        f"/ cold = {imagined * per_call / cold:.1f}x"
    )


if __name__ == "__main__":
    main()
