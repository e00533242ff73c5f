"""Envs written to check the library on envs it was never tuned for, each with a profile of
``make_env`` plus a lower bound and object labels (for reporting) and nothing else.

Both are :class:`~dorp_rl.envs.pieces.PiecesEnv` (stateless; its step reads ``step_count``
besides ``state``):

- ``ONE_COLOUR``: three white pieces that differ only in shape (an L, a bar, a square) on
  3 x 20 x 28 frames;
- ``LARGE_FRAMES``: a red square and a blue bar, 4 pixels a cell, on 3 x 64 x 64 frames;
- ``FOUR_GREY``: four pieces in grey shades (two of them white, differing in shape) on a
  12 x 12 grid drawn 3 pixels a cell, one-channel 1 x 36 x 36 frames;
- ``MINIGRID_EMPTY``: MiniGrid's Empty-16x16 through ``GymGoalEnv``, 3 x 80 x 80 frames.

Run one through every stage with the command::

    PYTHONPATH=benchmarks dorp evaluate --env untuned_envs:ONE_COLOUR --tasks 50 --name one-colour
"""

from __future__ import annotations

from dorp_rl.envs import EnvProfile
from dorp_rl.envs.pieces import PiecesEnv, cells_of, manhattan


def make_one_colour(batch_size=(8,), seed: int = 0, device=None) -> PiecesEnv:
    shapes = [cells_of(["#.", "#.", "##"]), cells_of(["####"]), cells_of(["##", "##"])]
    white = [(255, 255, 255)] * 3
    return PiecesEnv(shapes, white, (20, 28), 1, batch_size, seed, device)


def make_large_frames(batch_size=(8,), seed: int = 0, device=None) -> PiecesEnv:
    shapes = [cells_of(["##", "##"]), cells_of(["###"])]
    colours = [(230, 50, 50), (60, 90, 240)]
    return PiecesEnv(shapes, colours, (16, 16), 4, batch_size, seed, device)


def make_four_grey(batch_size=(8,), seed: int = 0, device=None) -> PiecesEnv:
    shapes = [
        cells_of(["##"]),
        cells_of(["#", "#"]),
        cells_of(["##", "##"]),
        cells_of(["#.", "##"]),
    ]
    shades = [(255, 255, 255), (255, 255, 255), (150, 150, 150), (90, 90, 90)]
    return PiecesEnv(shapes, shades, (12, 12), 3, batch_size, seed, device, channels=1)


def _objects(width: int):
    return lambda state: state[..., 0] * width + state[..., 1]


ONE_COLOUR = EnvProfile(
    name="one-colour-shapes",
    make_env=make_one_colour,
    lower_bound=manhattan,
    objects=_objects(28),
)
FOUR_GREY = EnvProfile(
    name="four-grey",
    make_env=make_four_grey,
    lower_bound=manhattan,
    objects=_objects(12),
)
LARGE_FRAMES = EnvProfile(
    name="large-frames",
    make_env=make_large_frames,
    lower_bound=manhattan,
    objects=_objects(16),
)


# ---------------------------------------------------------------- a gymnasium env
#: MiniGrid's Empty room, 16 x 16 cells (walls included) drawn at 5 pixels a cell by
#: MiniGrid's renderer: 3 x 80 x 80 frames; turn left, turn right, forward.
MINIGRID_ID, MINIGRID_TILE, MINIGRID_ACTIONS = "MiniGrid-Empty-16x16-v0", 5, 3


def make_empty_room_gym():
    import gymnasium as gym
    import minigrid  # noqa: F401  (registers the MiniGrid ids)

    env = gym.make(MINIGRID_ID, render_mode="rgb_array", tile_size=MINIGRID_TILE, highlight=False)

    class ThreeActions(gym.Wrapper):
        def __init__(self, inner):
            super().__init__(inner)
            self.action_space = gym.spaces.Discrete(MINIGRID_ACTIONS)

        def reset(self, *, seed=None, options=None):
            return self.env.reset(seed=0, options=options)

    return ThreeActions(env)


def empty_room_state(env) -> tuple[int, int, int]:
    """The agent's column, row and direction."""
    u = env.unwrapped
    return int(u.agent_pos[0]), int(u.agent_pos[1]), int(u.agent_dir)


def set_empty_room_state(env, state) -> None:
    u = env.unwrapped
    x, y, direction = (int(v) for v in state)
    u.agent_pos, u.agent_dir, u.step_count = (x, y), direction, 0


def make_empty_room(batch_size=(8,), seed: int = 0, device=None):
    from dorp_rl.envs import GymGoalEnv

    return GymGoalEnv(
        make_empty_room_gym,
        empty_room_state,
        set_empty_room_state,
        batch_size=batch_size,
        seed=seed,
        device=device,
    )


def _draw_reachable(env, num_tasks, seed):
    from dorp_rl.envs import draw_reachable_tasks

    return draw_reachable_tasks(env, num_tasks, seed)


MINIGRID_EMPTY = EnvProfile(
    name="minigrid-empty-16",
    make_env=make_empty_room,
    draw_tasks=_draw_reachable,
    # the agent's pose (column, row, direction) as one id
    objects=lambda state: (state[..., 0] * 10_000 + state[..., 1] * 100 + state[..., 2])[..., None],
)


def main() -> None:
    """Held-out selectivity and purity of a run's codes on one of these envs:
    ``python benchmarks/untuned_envs.py MINIGRID_EMPTY runs/minigrid-empty``."""
    import argparse

    import torch

    from dorp_rl.data import collect_play_data
    from dorp_rl.eval import play_object_diagnostics
    from dorp_rl.trainers import RepresentationConfig, load_encoder

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("profile", help="ONE_COLOUR, LARGE_FRAMES, FOUR_GREY or MINIGRID_EMPTY")
    parser.add_argument("run", help="the run folder of `dorp evaluate`")
    parser.add_argument("--frames", type=int, default=20_000, help="held-out play transitions")
    args = parser.parse_args()
    torch.set_num_threads(1)
    profile = globals()[args.profile]
    env = profile.build(batch_size=(8,))
    encoder = load_encoder(f"{args.run}/codes/checkpoints/last.pt", env)
    length = RepresentationConfig.for_env(profile).play_trajectory_length
    play = collect_play_data(env, args.frames, seed=1, trajectory_length=length, progress=False)
    out = play_object_diagnostics(play, encoder, profile.objects)
    purity = ", ".join(f"{p:.3f}" for p in out["purity"])
    print(f"{args.profile}: selectivity {out['selectivity']:.3f}, purity per one-hot {purity}")


if __name__ == "__main__":
    main()
