"""A profile of ``make_env`` only (plus reporting) for an env whose step reads ``step_count``.

Two white pieces that differ only in shape on a 3 x 12 x 16 canvas
(:class:`~dorp_rl.envs.pieces.PiecesEnv`); importable as ``counting_pieces`` so the
``dorp`` command takes it as ``--env counting_pieces:PROFILE``.
"""

from __future__ import annotations

from dorp_rl.envs import EnvProfile
from dorp_rl.envs.pieces import PiecesEnv, cells_of, manhattan


def make_env(batch_size=(4,), seed=0, device=None) -> PiecesEnv:
    shapes = [cells_of(["##", "#."]), cells_of(["###"])]
    return PiecesEnv(shapes, [(255, 255, 255)] * 2, (12, 16), 1, batch_size, seed, device)


PROFILE = EnvProfile(
    name="counting-pieces",
    make_env=make_env,
    lower_bound=manhattan,
    objects=lambda state: state[..., 0] * 16 + state[..., 1],
)


def make_large_env(batch_size=(4,), seed=0, device=None) -> PiecesEnv:
    """The same two pieces drawn 4 pixels a cell, in two colours: 3 x 48 x 64 frames."""
    shapes = [cells_of(["##", "#."]), cells_of(["###"])]
    colours = [(255, 255, 255), (240, 80, 80)]
    return PiecesEnv(shapes, colours, (12, 16), 4, batch_size, seed, device)


def make_large_one_colour_env(batch_size=(4,), seed=0, device=None) -> PiecesEnv:
    """The same two pieces drawn 4 pixels a cell, both white: 3 x 48 x 64 frames."""
    shapes = [cells_of(["##", "#."]), cells_of(["###"])]
    return PiecesEnv(shapes, [(255, 255, 255)] * 2, (12, 16), 4, batch_size, seed, device)
