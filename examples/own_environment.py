"""DORP on your own environment: an env written here, through play data, codes, graph and DORP.

``SlideShapesEnv`` (below) is not one of the library's envs: two shapes of different
colours (a red 2 x 3 bar and a green 3 x 3 cross) on a 3 x 24 x 32 canvas; action
``4 * shape + direction`` slides one shape one cell, unless it would leave the canvas or
overlap the other. It is a stateless, batched TorchRL env that starts from given states
on ``reset(td, set_state=True)``, which is all the library asks of it. Its profile
(``PROFILE``) tells the pipeline how to build it and, for reporting, a task's lower bound
and each shape's place; the library chooses everything else from the env's frames, and
nothing inside it is edited. The same env runs through the command::

    PYTHONPATH=examples dorp evaluate --env own_environment:PROFILE --tasks 20

Run: ``python examples/own_environment.py [--frames N] [--steps N] [--tasks 20]``;
with ``--low-level latent`` DORP plans through a latent world model trained here on the
env's play data and the codes (``--latent-steps``), instead of the env's own dynamics.
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.data import collect_play_data
from dorp_rl.envs import EnvProfile
from dorp_rl.eval import (
    evaluate_policy,
    make_task_set,
    play_code_dynamics,
    play_object_diagnostics,
)
from dorp_rl.planners import CodeGraph, encode_transitions
from dorp_rl.policies import make_dorp_policy
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    RepresentationConfig,
    RepresentationTrainer,
)

HEIGHT, WIDTH = 24, 32
MOVES = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]])  # up, down, left, right
#: each shape's cells relative to its top-left corner
SHAPES = [
    torch.tensor([[0, 0], [0, 1], [0, 2], [1, 0], [1, 1], [1, 2]]),  # 2 x 3 bar
    torch.tensor([[0, 1], [1, 0], [1, 1], [1, 2], [2, 1]]),  # 3 x 3 cross
]
COLOURS = torch.tensor([[230, 40, 40], [40, 200, 90]], dtype=torch.uint8)
SPAN = torch.tensor([[2, 3], [3, 3]])  # rows and columns each shape covers


class SlideShapesEnv(EnvBase):
    """Two shapes on a 3 x 24 x 32 canvas; ``state`` int64 ``[*B, 2, 2]`` (top-left cells).

    A task is solved (``terminated``) when ``state`` equals ``goal_state``. With
    ``batch_size=()`` and ``batch_locked=False`` it steps any leading shape, so it is its
    own true dynamics for planning.
    """

    _supports_set_state = True

    def __init__(self, batch_size=(8,), seed: int = 0, device=None, batch_locked: bool = True):
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        self.__dict__["_batch_locked"] = bool(batch_locked)
        b = self.batch_size
        image = Bounded(0, 255, (*b, 3, HEIGHT, WIDTH), dtype=torch.uint8)
        cells = Unbounded((*b, 2, 2), dtype=torch.int64)
        self.observation_spec = Composite(
            pixels=image, goal_pixels=image.clone(), state=cells, goal_state=cells.clone(), shape=b
        )
        self.action_spec = Categorical(8, shape=(*b, 1))
        self.reward_spec = Unbounded((*b, 1))
        self.rng = torch.Generator()
        self.set_seed(seed)

    def _set_seed(self, seed):
        self.rng.manual_seed(0 if seed is None else int(seed))

    @staticmethod
    def occupied(state: torch.Tensor) -> torch.Tensor:
        """Bool ``[*B, 2, H, W]``: the cells of each shape."""
        masks = torch.zeros(*state.shape[:-2], 2, HEIGHT, WIDTH, dtype=torch.bool)
        for k, cells in enumerate(SHAPES):
            rows = (state[..., k, 0, None] + cells[:, 0]).clamp(0, HEIGHT - 1)
            cols = (state[..., k, 1, None] + cells[:, 1]).clamp(0, WIDTH - 1)
            flat = masks[..., k, :, :].reshape(-1, HEIGHT * WIDTH)
            flat.scatter_(1, (rows * WIDTH + cols).reshape(flat.shape[0], -1), True)
            masks[..., k, :, :] = flat.reshape(*state.shape[:-2], HEIGHT, WIDTH)
        return masks

    def render(self, state: torch.Tensor) -> torch.Tensor:
        masks = self.occupied(state)  # [*B, 2, H, W]
        frames = torch.zeros(*state.shape[:-2], 3, HEIGHT, WIDTH, dtype=torch.uint8)
        for k in range(2):
            frames = torch.where(masks[..., k, None, :, :], COLOURS[k].view(3, 1, 1), frames)
        return frames

    def _valid(self, state: torch.Tensor) -> torch.Tensor:
        inside = ((state >= 0) & (state <= torch.tensor([HEIGHT, WIDTH]) - SPAN)).flatten(-2)
        overlap = self.occupied(state).all(-3).flatten(-2).any(-1)
        return inside.all(-1) & ~overlap

    def _draw(self, shape: torch.Size) -> torch.Tensor:
        state = torch.zeros(*shape, 2, 2, dtype=torch.int64)
        todo = torch.ones(shape, dtype=torch.bool)
        high = (torch.tensor([HEIGHT, WIDTH]) - SPAN + 1).float()
        while bool(todo.any()):
            draw = (torch.rand(*shape, 2, 2, generator=self.rng) * high).long()
            state = torch.where(todo[..., None, None], draw, state)
            todo = ~self._valid(state)
        return state

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size if tensordict is None else tensordict.batch_size
        given = tensordict if kwargs.get("set_state", False) else None
        out = {}
        for key in ("state", "goal_state"):
            value = None if given is None else given.get(key, None)
            out[key] = self._draw(shape) if value is None else value.clone()
        return TensorDict(
            pixels=self.render(out["state"]),
            goal_pixels=self.render(out["goal_state"]),
            **out,
            batch_size=shape,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        action = tensordict["action"].reshape(-1)
        state = tensordict["state"].reshape(-1, 2, 2)
        moved = state.clone()
        rows = torch.arange(state.shape[0])
        moved[rows, action // 4] += MOVES[action % 4]
        state = torch.where(self._valid(moved)[:, None, None], moved, state).reshape(*shape, 2, 2)
        goal = tensordict["goal_state"]
        solved = (state == goal).flatten(-2).all(-1, keepdim=True)
        return TensorDict(
            pixels=self.render(state),
            goal_pixels=tensordict["goal_pixels"],
            state=state,
            goal_state=goal,
            reward=solved.float(),
            done=solved,
            terminated=solved,
            batch_size=shape,
        )


def make_env(batch_size=(8,), seed: int = 0, device=None) -> SlideShapesEnv:
    """The factory the profile (and ``--env own_environment:make_env``) builds the env with."""
    return SlideShapesEnv(batch_size, seed=seed, device=device)


#: What the pipeline needs to know of this env, in one place: how to build it, and for
#: reporting, a lower bound of a task's steps and each shape's place (the labels of the
#: purity diagnostics). Everything else the library chooses from the env's frames (two
#: moving pieces: two one-hots whose maps compete) and writes to the run's log.
PROFILE = EnvProfile(
    name="slide-shapes",
    make_env=make_env,
    lower_bound=lambda env, state, goal: (state - goal).abs().flatten(-2).sum(-1),
    objects=lambda state: state[..., 0] * WIDTH + state[..., 1],
    description="a red bar and a green cross sliding on a 3 x 24 x 32 canvas",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--frames", type=int, default=None, help="play transitions (default: the library's)"
    )
    parser.add_argument(
        "--steps", type=int, default=None, help="code training steps (default: the library's)"
    )
    parser.add_argument("--tasks", type=int, default=20, help="seeded evaluation tasks")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="outputs/own_environment")
    parser.add_argument(
        "--low-level",
        choices=["gt", "latent"],
        default="gt",
        help="plan through the env's own dynamics or a latent world model trained here",
    )
    parser.add_argument("--latent-steps", type=int, default=3000, help="latent model steps")
    args = parser.parse_args()
    torch.set_num_threads(1)

    # 1. Codes: the library's defaults, trained on random play data of the env; what it
    # chose from the frames (the number of one-hots, ...) is printed and in chosen.json.
    budgets = {"num_frames": args.frames, "num_steps": args.steps}
    config = RepresentationConfig.for_env(
        PROFILE,
        seed=args.seed,
        out_dir=args.out,
        **{k: v for k, v in budgets.items() if v is not None},
    )
    trainer = RepresentationTrainer(config)
    for field, choice in trainer.chosen.items():
        print(f"chose {field} = {choice['value']}: {choice['why']}")
    trainer.train()
    diagnostics = trainer.evaluate()
    dynamics = diagnostics["code_dynamics"]  # label-free
    print(f"codes used per one-hot {dynamics['codes_used']}, dead {diagnostics['dead_onehots']}")

    print(f"change rate {dynamics['change_rate']}, undo rate {dynamics['undo_rate']}")
    encoder = trainer.encoder.eval()

    # 2. The code graph over the play data (one group per one-hot).
    play = collect_play_data(make_env(), 20_000, seed=args.seed + 1, trajectory_length=50)
    graph = CodeGraph.from_play_data(play, encoder, num_actions=8)
    print(f"graph nodes per group: {[graph.num_nodes(g) for g in range(graph.num_groups)]}")
    codes = encode_transitions(play, encoder)  # once, for both diagnostics
    dead = play_code_dynamics(play, encoder, transitions=codes)["dead"]
    print(f"dead one-hots on new play: {dead}")
    # Ground truth from the profile's objects mapping, on this held-out play data.
    labelled = play_object_diagnostics(play, encoder, PROFILE.objects, transitions=codes)
    print(
        f"held-out play: selectivity {labelled['selectivity']:.3f}, purity per one-hot "
        f"{[round(p, 3) for p in labelled['purity']]} (object of each one-hot: "
        f"{labelled['onehot_object']})"
    )

    # 3. DORP with the env's true dynamics (the env itself, unbatched, steps any shape),
    # or with a latent world model of the codes learned from play data.
    env = make_env(batch_size=(10,), seed=args.seed)
    if args.low_level == "latent":
        latent_config = LatentWorldModelConfig.for_env(
            PROFILE, num_steps=args.latent_steps, seed=args.seed, out_dir=f"{args.out}/latent_model"
        )
        latent = LatentWorldModelTrainer(latent_config, encoder=encoder)
        accuracy = latent.train()["evaluation"]["code_accuracy"]
        print(
            f"latent model: codes right at open-loop steps 1 / last {accuracy[0]} / {accuracy[-1]}"
        )
        model = latent.model.eval()
    else:
        model = SlideShapesEnv(batch_size=(), batch_locked=False)
    policy = make_dorp_policy(env, encoder, graph, low_level=model, seed=args.seed)
    tasks = make_task_set(env, args.tasks, seed=args.seed, profile=PROFILE)
    limit = PROFILE.task_limit(env=env)
    out = evaluate_policy(env, policy, tasks, max_steps=limit, tasks_per_rollout=10, seed=0)
    bounds = tasks["lower_bound"].tolist()
    solved = [s / b for s, b, ok in zip(out["steps"], bounds, out["success"], strict=True) if ok]
    ratio = sum(solved) / max(len(solved), 1)
    print(
        f"DORP: solved {sum(out['success'])} of {args.tasks}, {out['mean_steps']:.1f} steps "
        f"(lower bound {out['mean_lower_bound']:.1f}; {ratio:.2f}x the bound per task)"
    )


if __name__ == "__main__":
    main()
