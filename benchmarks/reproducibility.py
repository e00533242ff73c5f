"""What a seeded run reproduces: bit for bit on the same machine, and where it parts.

Each variant runs one tiny seeded pipeline in a fresh process: play data, a short code
training (``RepresentationConfig.rearrangement``), the code graph over the play data and
the DORP policy on a seeded task set with the true dynamics. The process prints a
digest of the trained encoder's weights, the codes of the play frames, the graph's nodes
and the per-task steps; the variants are compared with the first one.

Variants (``--variants``):

- ``same``: the reference command again (same machine, same threads);
- ``threads2``: two torch threads instead of one;
- ``avx2`` / ``default``: torch's CPU kernels for another instruction set
  (``ATEN_CPU_CAPABILITY``; ``default`` is without vector instructions), which is what a
  machine without AVX-512 (or an older one) runs. Only capabilities the CPU has can be
  chosen; this machine's own is printed.

Usage::

    .venv/bin/python benchmarks/reproducibility.py --objects 2 --steps 300 --frames 20000
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

VARIANTS = {
    "reference": ({}, 1),
    "same": ({}, 1),
    "threads2": ({}, 2),
    "avx2": ({"ATEN_CPU_CAPABILITY": "avx2"}, 1),
    "default": ({"ATEN_CPU_CAPABILITY": "default"}, 1),
}


def _digest(tensor) -> str:
    return hashlib.sha256(tensor.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16]


def run_once(args: argparse.Namespace) -> dict:
    """The pipeline in this process; returns its digests and figures."""
    import torch

    from dorp_rl.eval import SETTINGS, evaluate_policy, make_task_set
    from dorp_rl.planners import CodeGraph
    from dorp_rl.policies import make_dorp_policy
    from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer

    torch.set_num_threads(args.threads)
    setting = SETTINGS[f"{args.objects}obj"]
    out = Path(args.out)
    cfg = RepresentationConfig.for_env(
        setting.env,
        setting.num_objects,
        num_steps=args.steps,
        num_frames=args.frames,
        seed=0,
        out_dir=str(out / "codes"),
        data_dir=str(out / "play"),
        progress=False,
        threads=args.threads,
        checkpoint_every=args.steps,
    )
    trainer = RepresentationTrainer(cfg)
    trainer.train()
    encoder = trainer.encoder.eval()
    weights = torch.cat([p.detach().reshape(-1) for p in encoder.state_dict().values()])
    frames = trainer.buffer.storage[torch.arange(len(trainer.buffer))]["pixels"]
    codes = encoder.encode(frames)
    graph = CodeGraph.from_play_data(trainer.buffer, encoder, setting.groups)
    env = setting.make_env(batch_size=(10,), seed=0)
    policy = make_dorp_policy(env, encoder, graph, num_candidates=args.candidates, seed=0)
    result = evaluate_policy(
        env, policy, make_task_set(env, args.tasks, seed=0), tasks_per_rollout=10, seed=0
    )
    return {
        "weights": _digest(weights),
        "weights_values": weights.tolist(),
        "codes": _digest(codes),
        "codes_values": codes.tolist(),
        "graph_nodes": [graph.num_nodes(g) for g in range(graph.num_groups)],
        "steps": result["steps"],
        "success_rate": result["success_rate"],
        "capability": torch.backends.cpu.get_cpu_capability(),
    }


def compare(reference: dict, other: dict) -> dict:
    import torch

    a, b = torch.tensor(reference["weights_values"]), torch.tensor(other["weights_values"])
    ca, cb = torch.tensor(reference["codes_values"]), torch.tensor(other["codes_values"])
    # Codes are labels: match each of the reference's codes to the other run's most
    # frequent code on the same frames, per one-hot, and count the frames that disagree.
    matched = torch.zeros_like(ca, dtype=torch.bool)
    for j in range(ca.shape[1]):
        for code in ca[:, j].unique():
            rows = ca[:, j] == code
            matched[rows, j] = cb[rows, j] == cb[rows, j].mode().values
    return {
        "weights identical": reference["weights"] == other["weights"],
        "frames in other code regions": float((~matched).any(-1).float().mean()),
        "max weight difference": float((a - b).abs().max()),
        "frames with other codes": float((ca != cb).any(-1).float().mean()),  # labels
        "graph nodes": other["graph_nodes"],
        "tasks with other steps": sum(
            x != y for x, y in zip(reference["steps"], other["steps"], strict=True)
        ),
        "success": other["success_rate"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=2)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--candidates", type=int, default=300)
    parser.add_argument("--variants", nargs="+", default=["same", "threads2", "avx2", "default"])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--out", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(run_once(args)))
        return
    results, seconds = {}, {}
    for name in ["reference", *args.variants]:
        extra_env, threads = VARIANTS[name]
        with tempfile.TemporaryDirectory() as tmp:
            command = [sys.executable, __file__, "--worker", "--out", tmp,
                       "--threads", str(threads), "--objects", str(args.objects),
                       "--steps", str(args.steps), "--frames", str(args.frames),
                       "--tasks", str(args.tasks), "--candidates", str(args.candidates)]  # fmt: skip
            env = {**os.environ, "OMP_NUM_THREADS": str(threads), **extra_env}
            start = time.perf_counter()
            done = subprocess.run(command, env=env, capture_output=True, text=True)
            seconds[name] = time.perf_counter() - start
        if done.returncode != 0:
            print(f"{name}: failed\n{done.stderr[-2000:]}")
            continue
        results[name] = json.loads(done.stdout.strip().splitlines()[-1])
    reference = results["reference"]
    print(
        f"{args.objects} objects, {args.steps} code steps on {args.frames} play frames, "
        f"DORP on {args.tasks} tasks; this CPU's capability: {reference['capability']}"
    )
    print(
        "| variant | kernels | weights identical | max weight difference | frames with other "
        "code labels | frames in other code regions | graph nodes | tasks with other steps | "
        "success | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, result in results.items():
        row = compare(reference, result)
        print(
            f"| {name} | {result['capability']} | {row['weights identical']} | "
            f"{row['max weight difference']:.3g} | {row['frames with other codes']:.4f} | "
            f"{row['frames in other code regions']:.4f} | "
            f"{row['graph nodes']} | {row['tasks with other steps']} of {len(result['steps'])} | "
            f"{row['success']:.2f} | {seconds[name]:.0f} |"
        )


if __name__ == "__main__":
    main()
