"""Where a key-wall encoder's agent map puts its mass, and what the key changes in it.

Reads a representation checkpoint (``outputs/.../checkpoints/last.pt``) and, over every
start-able cell without the key and the same cell with it (the key events of
``key_room_diagnostics``), reports:

- the agent map's mean value on the agent's own pixel and its total mass;
- how much the key's removal changes the agent map in total, on the key's pixel and on
  the door's pixels;
- the agent codes without and with the key, as in the paper's Figure 6(a, b).

This is the measurement behind docs/NOTES.md, "Key-wall codes": with the preset before
the motion-coverage term the agent map held almost nothing on the agent (mean value
< 0.001) and the key's removal changed it more than the agent's own signal did; with the
current preset the map sits on the agent (docs/RESULTS.md, "Key-wall").

    python benchmarks/key_wall_maps.py outputs/representation_quality/keywall-dddp-seed1/checkpoints/last.pt
"""

from __future__ import annotations

import argparse

import torch
from bench_threads import add_threads_argument, parse_with_threads

from dorp_rl.envs import KeyWallEnv, key_event_states, key_room_diagnostics
from dorp_rl.trainers.representation import load_encoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    add_threads_argument(parser)
    args = parse_with_threads(parser)

    env = KeyWallEnv()
    encoder = load_encoder(args.checkpoint, env=env)
    diag = key_room_diagnostics(env, encoder.encode, with_steps=False)
    agent = diag["agent_onehot"]
    print(
        f"agent one-hot {agent}, key one-hot {diag['key_onehot']}, agent one-hot unchanged "
        f"on key events {diag['agent_onehot_unchanged_fraction']:.3f}"
    )
    for name in ("code_map_without_key", "code_map_with_key"):
        print(name)
        for row in diag[name]:
            print(" ".join(f"{c:2d}" if c >= 0 else " ." for c in row))

    without_key, with_key = key_event_states(env)
    rows, cols = without_key[:, 0], without_key[:, 1]
    with torch.no_grad():
        _, maps_without = encoder.logits_and_maps(env.render_state(without_key))
        _, maps_with = encoder.logits_and_maps(env.render_state(with_key))
    agent_without, agent_with = maps_without[:, agent], maps_with[:, agent]
    change = (agent_with - agent_without).abs()  # [cells, 16, 16]
    on_agent = agent_without[torch.arange(len(rows)), rows, cols]
    print(f"agent map on the agent's pixel (mean)      {on_agent.mean():.4f}")
    print(f"agent map mass (mean sum over pixels)      {agent_without.sum((-2, -1)).mean():.3f}")
    print(f"change when the key is taken: total        {change.sum((-2, -1)).mean():.3f}")
    print(f"                              on the key   {change[:, env.key].sum(-1).mean():.3f}")
    print(f"                              on the door  {change[:, env.door].sum(-1).mean():.3f}")


if __name__ == "__main__":
    main()
