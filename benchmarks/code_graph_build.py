"""Building a CodeGraph from a large play buffer, and the cost of one shortest-path query.

Collects ``--frames`` transitions of 5-object rearrangement play, encodes both frames of
each with a trained encoder (``--checkpoint``), and builds the graphs with groups
``"onehot"`` and ``(0, 1), (2, 3, 4)``, timing encoding and building separately. Then it
times :meth:`~dorp_rl.planners.CodeGraph.next_waypoint` between random start and goal
codes of the data for a one-hot, a pair and a triple group, without removed edges (a
table lookup where the group has a distance table) and with one removed edge (a
breadth-first search), and prints medians. Build time is set against encoding time in
the same run.

    python benchmarks/code_graph_build.py --frames 1000000 --threads 1
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from bench_threads import add_threads_argument, parse_with_threads

from dorp_rl.data import collect_play_data
from dorp_rl.envs import ObjectRearrangementEnv
from dorp_rl.planners import CodeGraph, encode_transitions
from dorp_rl.trainers import load_encoder


def query_ms(graph: CodeGraph, group: int, codes: torch.Tensor, removed: bool, n: int) -> float:
    """Median ms of ``next_waypoint`` between ``n`` random pairs of data codes."""
    gen = torch.Generator().manual_seed(group)
    times = []
    for _ in range(n):
        a, b = codes[torch.randint(0, codes.shape[0], (2,), generator=gen)]
        start, goal = int(graph.node_of(a, group)), int(graph.node_of(b, group))
        if start == goal:
            continue
        cut = None
        if removed:  # remove the first edge of a shortest path, so a search is needed
            _, edge, _ = graph.next_waypoint(start, goal)
            cut = torch.tensor([edge])
        begin = time.perf_counter()
        graph.next_waypoint(start, goal, cut)
        times.append(1000 * (time.perf_counter() - begin))
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1_000_000)
    parser.add_argument(
        "--checkpoint", default="outputs/codes/rearrangement5-seed0/checkpoints/last.pt"
    )
    parser.add_argument("--queries", type=int, default=50)
    add_threads_argument(parser)
    args = parse_with_threads(parser)
    env = ObjectRearrangementEnv(num_objects=5, batch_size=(256,))
    encoder = load_encoder(args.checkpoint, env)
    start = time.perf_counter()
    buffer = collect_play_data(env, args.frames, seed=1)
    print(f"play data: {args.frames} transitions in {time.perf_counter() - start:.1f} s")
    start = time.perf_counter()
    codes, next_codes = encode_transitions(buffer, encoder, progress=True)
    encode_s = time.perf_counter() - start
    print(f"encoding {2 * args.frames} frames: {encode_s:.1f} s")
    for groups in ("onehot", [(0, 1), (2, 3, 4)]):
        start = time.perf_counter()
        graph = CodeGraph.from_transitions(codes, next_codes, encoder.code_sizes, groups)
        build_s = time.perf_counter() - start
        sizes = ", ".join(
            f"{tuple(m)}: {graph.num_nodes(g)} nodes / {graph.num_edges(g)} edges"
            for g, m in enumerate(graph.groups)
        )
        print(f"graph {groups}: {build_s:.2f} s ({build_s / encode_s:.3f}x encoding); {sizes}")
        for g, members in enumerate(graph.groups):
            if g > 0 and groups == "onehot":
                break
            kind = {1: "one-hot", 2: "pair", 3: "triple"}[len(members)]
            plain = query_ms(graph, g, codes, False, args.queries)
            cut = query_ms(graph, g, codes, True, args.queries)
            print(
                f"  query, {kind} {tuple(members)}: {plain:.3f} ms; "
                f"with a removed edge {cut:.3f} ms"
            )


if __name__ == "__main__":
    main()
