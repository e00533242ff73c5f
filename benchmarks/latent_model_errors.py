"""Where a trained latent world model's one-step code errors come from, by one-hot and action.

On held-out play windows (another seed than training's, as the trainer evaluates):

- ``head_accuracy``: the code head's codes of the *encoded* true frames equal the DORP
  encoder's codes (every one-hot): the ceiling the dynamics can only lower;
- ``one_step_accuracy``: the same after one imagined step from the encoded true frame;
- per one-hot, the one-step error on steps where the encoder's code of that one-hot
  changed and where it did not;
- per action, over the steps where the frame changed: the share whose imagined latent is
  nearer the encoding of the next true frame than of the frame it started from (near 0:
  the model leaves the scene as it was after that action);
- ``open_loop_accuracy``: codes right over the windows' steps (open loop, as the trainer
  measures it) in float32 and in bfloat16 (:func:`torch.autocast`, as a planning env
  imagines where the hardware runs bfloat16 natively).

    python benchmarks/latent_model_errors.py --env rearrangement --num-objects 5 \\
        --codes runs/<run>/5obj-seed0/codes/checkpoints/last.pt --model <latent checkpoint>
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from dorp_rl.metrics import latent_open_loop_accuracy
from dorp_rl.objectives import LatentWorldModelLoss
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    load_encoder,
    load_latent_world_model,
)


@torch.no_grad()
def one_step_errors(model: torch.nn.Module, encoder: torch.nn.Module, windows) -> dict:
    """The figures above on ``[N, H]`` windows with int64 action indices ``[N, H, 1]``."""
    loss = LatentWorldModelLoss(model, encoder)
    frames, action = loss._read(windows)  # [N, H + 1, C, H', W'], [N, H]
    truth = loss.target_codes(frames)  # [N, H + 1, K]
    encoded = model.encode(frames)
    head = model.codes(encoded)
    stepped = model.step(encoded[:, :-1], action)
    one = model.codes(stepped)
    wrong = one != truth[:, 1:]  # [N, H, K]
    changed = truth[:, 1:] != truth[:, :-1]
    per_one_hot = [
        {
            "error_when_changed": round(float(wrong[..., k][changed[..., k]].float().mean()), 4),
            "changes": int(changed[..., k].sum()),
            "error_when_unchanged": round(float(wrong[..., k][~changed[..., k]].float().mean()), 4),
        }
        for k in range(truth.shape[-1])
    ]
    moved = (frames[:, 1:] != frames[:, :-1]).flatten(2).any(-1)  # [N, H]
    nearer_next = (stepped - encoded[:, 1:]).norm(dim=-1) < (stepped - encoded[:, :-1]).norm(dim=-1)
    per_action = {}
    for a in range(model.num_actions):
        chosen = moved & (action == a)
        if chosen.any():
            per_action[a] = {
                "moves": int(chosen.sum()),
                "nearer_next": round(float(nearer_next[chosen].float().mean()), 3),
            }
    return {
        "head_accuracy": round(float((head == truth).all(-1).float().mean()), 4),
        "one_step_accuracy": round(float((~wrong).all(-1).float().mean()), 4),
        "per_one_hot": per_one_hot,
        "per_action": per_action,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="rearrangement", help="env profile")
    parser.add_argument("--num-objects", type=int, default=None)
    parser.add_argument("--codes", required=True, help="the representation checkpoint")
    parser.add_argument("--model", required=True, help="the latent world-model checkpoint")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out-dir", default="outputs/latent_model_errors")
    parser.add_argument("--json", default=None, help="write the result here too")
    parser.add_argument("--eval-windows", type=int, default=4096, help="held-out windows")
    parser.add_argument(
        "--eval-frames", type=int, default=64_000, help="held-out play transitions they come from"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    # The trainer's held-out windows (its eval seed), with a token training buffer.
    cfg = LatentWorldModelConfig.for_env(
        args.env,
        args.num_objects,
        num_frames=4000,
        num_steps=1,
        out_dir=args.out_dir,
        eval_sequences=args.eval_windows,
        eval_frames=args.eval_frames,
    )
    cfg = cfg.replace(progress=False)
    env = cfg.make_env(batch_size=(cfg.num_envs,))
    encoder = load_encoder(args.codes, env)
    trainer = LatentWorldModelTrainer(cfg, encoder=encoder)
    model = load_latent_world_model(args.model, env, encoder)
    windows = trainer.eval_windows.clone()
    windows.set("action", trainer.actions.index(windows.get("action")))
    out = {"env": args.env, "num_objects": cfg.num_objects, "model": args.model}
    out.update(one_step_errors(model, encoder, windows))
    out["open_loop_accuracy"] = {}
    for dtype in (torch.float32, torch.bfloat16):
        with torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32):
            steps = latent_open_loop_accuracy(model, encoder, windows)["code_accuracy"]
        out["open_loop_accuracy"][str(dtype).removeprefix("torch.")] = round(
            sum(steps) / len(steps), 4
        )
    print(json.dumps(out))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
