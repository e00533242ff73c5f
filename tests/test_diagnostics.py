"""Code-quality diagnostics (``dorp_rl.metrics.diagnostics``) and their pictures.

The encoders here are hand-made from the true state, read back from the pixels (the
diagnostics only ever give ``encode`` pixels): an oracle (one one-hot per object, code =
the object's coarse 4x4 cell) must score perfectly, a permuted oracle too under the
permuted assignment, and a hash of the pixels or an entangled encoder must not.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch

from dorp_rl.envs import (
    OBJECT_COLOURS,
    KeyCorridorEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    key_room_code_maps,
    key_room_diagnostics,
    plot_key_room_code_map,
    rearrangement_code_maps,
    rearrangement_diagnostics,
)
from dorp_rl.envs.key_rooms import AGENT_COLOUR, DOOR_COLOUR
from dorp_rl.metrics.diagnostics import best_assignment, connected_fraction, encode_pixels
from dorp_rl.viz.code_maps import (
    plot_code_maps,
    plot_factorization_histogram,
    write_diagnostic_plots,
)

Encoder = Callable[[torch.Tensor], torch.Tensor]
SAMPLES = 2048
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@functools.cache
def rearrangement(k: int) -> ObjectRearrangementEnv:
    return ObjectRearrangementEnv(num_objects=k, seed=0)


@functools.cache
def key_wall() -> KeyWallEnv:
    """Shared so that its exact distance table (a BFS over 512 states) is built once."""
    return KeyWallEnv(seed=0)


# ---------------------------------------------------------------------- #
# Hand-made encoders (all read the state back from the pixels)
# ---------------------------------------------------------------------- #
def first_pixel(pixels: torch.Tensor, colour: torch.Tensor) -> torch.Tensor:
    """Top-left (row, col) of the pixels of ``colour`` [..., 3]: int64 [N, ..., 2]."""
    match = (pixels[:, None] == colour.view(1, -1, 3, 1, 1)).all(2)  # [N, L, 16, 16]
    rows = match.any(-1).float().argmax(-1)
    cols = match.any(-2).float().argmax(-1)
    return torch.stack([rows, cols], dim=-1)


def coarse(corner: torch.Tensor) -> torch.Tensor:
    """16 codes: the 4x4 cell of a (row, col) position."""
    return (corner[..., 0] // 4) * 4 + corner[..., 1] // 4


def rearrangement_oracle(k: int, order: list[int] | None = None) -> Encoder:
    """One one-hot per object, code = coarse cell; one-hot ``c`` tracks object ``order[c]``."""
    order = list(range(k)) if order is None else order

    def encode(pixels: torch.Tensor) -> torch.Tensor:
        return coarse(first_pixel(pixels, OBJECT_COLOURS[:k]))[:, order]

    return encode


def hash_encoder(num_onehots: int, num_codes: int = 16, seed: int = 0) -> Encoder:
    """A deterministic function of the pixels that knows nothing about objects."""
    weights = torch.randint(
        1, 2**20, (3 * 16 * 16, num_onehots), generator=torch.Generator().manual_seed(seed)
    )

    def encode(pixels: torch.Tensor) -> torch.Tensor:
        return (pixels.flatten(1).long() @ weights) % 1_000_003 % num_codes

    return encode


def entangled_encoder(pixels: torch.Tensor) -> torch.Tensor:
    """One-hot 0 tracks both objects, one-hot 1 tracks object 1 only."""
    cells = coarse(first_pixel(pixels, OBJECT_COLOURS[:2]))  # [N, 2]
    return torch.stack([cells[:, 0] * 16 + cells[:, 1], cells[:, 1]], dim=-1)


def key_wall_oracle(key_first: bool = False, agent_sees_key: bool = False) -> Encoder:
    """Agent one-hot = coarse agent cell, key bit = the door is gone."""

    def encode(pixels: torch.Tensor) -> torch.Tensor:
        agent = coarse(first_pixel(pixels, torch.tensor([AGENT_COLOUR], dtype=torch.uint8))[:, 0])
        door = torch.tensor(DOOR_COLOUR, dtype=torch.uint8).view(3, 1, 1)
        has_key = (~(pixels == door).all(1).flatten(1).any(1)).long()
        if agent_sees_key:
            agent = agent + 16 * has_key
        pair = [has_key, agent] if key_first else [agent, has_key]
        return torch.stack(pair, dim=-1)

    return encode


# ---------------------------------------------------------------------- #
# Rearrangement
# ---------------------------------------------------------------------- #
@pytest.mark.parametrize("k", [2, 3])
def test_oracle_scores_perfectly(k: int) -> None:
    result = rearrangement_diagnostics(rearrangement(k), rearrangement_oracle(k), SAMPLES)
    assert result["assignment"] == list(range(k))
    assert result["selectivity"] == 1.0
    assert result["purity"] == [1.0] * k and result["min_purity"] == 1.0
    assert result["frac_at_most_one_change"] == 1.0
    assert result["connected_fraction"] == [1.0] * k
    assert result["codes_used"] == [16] * k and result["min_codes_used"] == 16
    assert result["num_moves"] == sum(result["moves_per_object"]) > 0.9 * SAMPLES
    # Off-diagonal: moving one object never changes another's one-hot.
    matrix = torch.tensor(result["change_matrix"])
    assert (matrix - torch.diag(matrix.diag()) == 0).all() and (matrix.diag() > 0).all()
    # Two states sharing a 4x4 cell are close; two random states are not.
    for within, baseline in zip(
        result["mean_steps_within_code"], result["mean_steps_random_pair"], strict=True
    ):
        assert within < 3.5 < 7.0 < baseline
    json.dumps(result)  # plain numbers and lists only


def test_permuted_oracle_finds_the_permutation() -> None:
    order = [2, 0, 1]  # one-hot c tracks object order[c]
    result = rearrangement_diagnostics(rearrangement(3), rearrangement_oracle(3, order), SAMPLES)
    assert result["selectivity"] == 1.0
    assert result["assignment"] == [1, 2, 0]  # object o -> one-hot order.index(o)
    assert result["onehot_object"] == order
    assert result["min_purity"] == 1.0


def test_hash_encoder_is_at_chance() -> None:
    result = rearrangement_diagnostics(rearrangement(2), hash_encoder(2), SAMPLES)
    assert 0.35 < result["selectivity"] < 0.65  # chance is 1 / 2
    assert max(result["purity"]) < 0.5
    assert result["frac_at_most_one_change"] < 0.5
    assert max(result["mean_steps_within_code"]) > 7.0  # codes say nothing about position


def test_one_onehot_tracking_both_objects_is_penalised() -> None:
    result = rearrangement_diagnostics(rearrangement(2), entangled_encoder, SAMPLES)
    assert result["assignment"] == [0, 1]
    # Object 1's moves change both one-hots: about 2/3 of the changes are on target.
    assert 0.5 < result["selectivity"] < 0.8
    assert result["purity"][0] < 0.5 < result["purity"][1] == 1.0
    # The naive score cannot tell: most moves still change at most one one-hot.
    assert result["frac_at_most_one_change"] > 0.8


def test_more_onehots_than_objects() -> None:
    oracle = rearrangement_oracle(2)

    def with_constant(pixels: torch.Tensor) -> torch.Tensor:
        codes = oracle(pixels)
        return torch.cat([torch.zeros_like(codes[:, :1]), codes], dim=-1)

    result = rearrangement_diagnostics(rearrangement(2), with_constant, SAMPLES)
    assert result["assignment"] == [1, 2] and result["onehot_object"] == [None, 0, 1]
    assert result["selectivity"] == 1.0 and result["min_purity"] == 1.0
    assert math.isnan(result["purity"][0]) and result["code_maps"][0] is None
    assert result["codes_used"] == [1, 16, 16] and result["min_codes_used"] == 16


def test_fewer_onehots_than_objects() -> None:
    result = rearrangement_diagnostics(rearrangement(3), rearrangement_oracle(3, [0, 2]), SAMPLES)
    assert result["assignment"] == [0, None, 1]
    assert result["change_matrix"][1] == [0, 0]  # no one-hot follows object 1
    assert result["selectivity"] == 1.0 and result["purity"] == [1.0, 1.0]


def test_seeded_and_leaves_the_env_generator_alone() -> None:
    env = rearrangement(2)
    before = env.rng.get_state()
    first = rearrangement_diagnostics(env, hash_encoder(2), 256, seed=3)
    assert torch.equal(env.rng.get_state(), before)
    second = rearrangement_diagnostics(env, hash_encoder(2), 256, seed=3)
    assert json.dumps(first) == json.dumps(second)
    other = rearrangement_diagnostics(env, hash_encoder(2), 256, seed=4)
    assert other["change_matrix"] != first["change_matrix"]


def test_one_object_code_map_is_exact() -> None:
    env = rearrangement(1)
    (code_map,) = rearrangement_code_maps(env, rearrangement_oracle(1))
    rows, cols = torch.meshgrid(torch.arange(15), torch.arange(13), indexing="ij")
    assert torch.equal(code_map, (rows // 4) * 4 + cols // 4)
    result = rearrangement_diagnostics(env, rearrangement_oracle(1), SAMPLES)
    assert torch.equal(torch.tensor(result["code_maps"][0]), code_map)  # all positions seen


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (lambda px: torch.zeros(len(px), dtype=torch.int64), r"shape \[N, C\]"),
        (lambda px: torch.zeros(len(px), 2), "int64"),
        (lambda px: torch.zeros(len(px) + 1, 2, dtype=torch.int64), r"\[N, C\]"),
        (lambda px: torch.full((len(px), 2), -1, dtype=torch.int64), ">= 0"),
        (lambda px: px.flatten(1).numpy(), "int64"),
    ],
)
def test_wrong_encoder_output_is_a_clear_error(bad: Encoder, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        rearrangement_diagnostics(rearrangement(2), bad, 64)
    with pytest.raises(ValueError, match=match):
        key_room_diagnostics(key_wall(), bad)


def test_onehot_count_must_not_change_between_chunks() -> None:
    calls = iter([2, 3])

    def fickle(pixels: torch.Tensor) -> torch.Tensor:
        return torch.zeros(len(pixels), next(calls), dtype=torch.int64)

    pixels = torch.zeros(10, 3, 16, 16, dtype=torch.uint8)
    with pytest.raises(ValueError, match=r"\[5, 2\]"):
        encode_pixels(fickle, pixels, chunk_size=5)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="uint8"):
        encode_pixels(rearrangement_oracle(1), torch.zeros(2, 3, 16, 16))
    with pytest.raises(ValueError, match="ObjectRearrangementEnv"):
        rearrangement_diagnostics(key_wall(), rearrangement_oracle(1))
    with pytest.raises(ValueError, match="KeyRoomEnv"):
        key_room_diagnostics(rearrangement(1), rearrangement_oracle(1))
    with pytest.raises(ValueError, match="at least 2 one-hots"):
        key_room_diagnostics(key_wall(), lambda px: key_wall_oracle()(px)[:, :1])


# ---------------------------------------------------------------------- #
# Generic pieces
# ---------------------------------------------------------------------- #
@pytest.mark.parametrize(("rows", "cols"), [(1, 1), (2, 3), (3, 3), (4, 2), (5, 6)])
def test_best_assignment_matches_brute_force(rows: int, cols: int) -> None:
    gen = np.random.default_rng(rows * 10 + cols)
    for _ in range(5):
        scores = gen.integers(0, 20, size=(rows, cols)).astype(float)
        got = best_assignment(scores)
        assert len(got) == rows
        chosen = [(r, c) for r, c in enumerate(got) if c is not None]
        assert len({c for _, c in chosen}) == len(chosen) == min(rows, cols)
        if rows <= cols:
            best = max(
                sum(scores[r, c] for r, c in enumerate(p))
                for p in itertools.permutations(range(cols), rows)
            )
        else:
            best = max(
                sum(scores[r, c] for c, r in enumerate(p))
                for p in itertools.permutations(range(rows), cols)
            )
        assert sum(scores[r, c] for r, c in chosen) == best


def test_connected_fraction() -> None:
    code_map = torch.tensor(
        [
            [0, 0, -1, 0],
            [1, 1, -1, 2],
            [1, -1, 3, 2],
            [3, 3, 2, 2],
        ]
    )
    # 0 is split by the gap; 1 is connected; 2 is connected; 3 touches only diagonally.
    assert connected_fraction(code_map) == (0.5, 4)
    assert math.isnan(connected_fraction(torch.full((3, 3), -1))[0])


# ---------------------------------------------------------------------- #
# Key rooms
# ---------------------------------------------------------------------- #
def test_key_wall_oracle() -> None:
    env = key_wall()
    result = key_room_diagnostics(env, key_wall_oracle(key_first=True))
    assert (result["key_onehot"], result["agent_onehot"]) == (0, 1)  # inferred
    assert result["num_key_events"] == len(env.start_cells) == 127
    assert result["key_bit_change_fraction"] == 1.0
    assert result["agent_onehot_unchanged_fraction"] == 1.0
    assert result["move_selectivity"] == 1.0
    assert 0.0 < result["move_agent_change_fraction"] < 0.5
    assert result["connected_fraction_without_key"] == 1.0
    assert result["connected_fraction_with_key"] == 1.0
    assert (result["codes_used_without_key"], result["codes_used_with_key"]) == (8, 16)
    assert result["key_codes_used"] == 2
    for name in ("without_key", "with_key"):
        within = result[f"mean_steps_within_code_{name}"]
        assert within < 4.0 < result[f"mean_steps_random_pair_{name}"]
    maps = torch.tensor(result["code_map_without_key"]), torch.tensor(result["code_map_with_key"])
    assert (maps[0][env.wall] == -1).all() and (maps[1][env.wall] == -1).all()
    assert maps[0][0, 0] == -1 and maps[1][0, 0] == 0  # the key cell: only with the key
    assert (maps[0][:, 9:] == -1).all()  # the locked room
    json.dumps(result)


def test_key_wall_agent_code_that_sees_the_key() -> None:
    result = key_room_diagnostics(
        key_wall(), key_wall_oracle(agent_sees_key=True), key_onehot=1, with_steps=False
    )
    assert result["key_bit_change_fraction"] == 1.0
    assert result["agent_onehot_unchanged_fraction"] == 0.0
    assert math.isnan(result["mean_steps_within_code_with_key"])


def test_key_wall_given_onehots_are_checked() -> None:
    with pytest.raises(ValueError, match="key_onehot"):
        key_room_diagnostics(key_wall(), key_wall_oracle(), key_onehot=2)
    with pytest.raises(ValueError, match="differ"):
        key_room_diagnostics(key_wall(), key_wall_oracle(), key_onehot=1, agent_onehot=1)


def test_key_corridor_runs() -> None:
    env = KeyCorridorEnv(seed=0)
    result = key_room_diagnostics(env, key_wall_oracle(), with_steps=False)
    assert result["key_onehot"] == 1 and result["key_bit_change_fraction"] == 1.0
    assert result["agent_onehot_unchanged_fraction"] == 1.0
    without_key, with_key = key_room_code_maps(env, key_wall_oracle())
    assert without_key.shape == with_key.shape == (16, 16)
    assert (with_key[env.wall] == -1).all() and (with_key[~env.wall] >= 0).all()


# ---------------------------------------------------------------------- #
# Pictures
# ---------------------------------------------------------------------- #
def _is_png(path) -> bool:
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize(
    ("env", "encode"),
    [
        (rearrangement(1), rearrangement_oracle(1)),
        (rearrangement(2), hash_encoder(3)),
        (key_wall(), key_wall_oracle()),
    ],
    ids=["rearrangement-1", "rearrangement-2", "key-wall"],
)
def test_write_diagnostic_plots(env, encode: Encoder, tmp_path) -> None:
    paths = write_diagnostic_plots(env, encode, tmp_path / "plots", num_samples=512)
    assert set(paths) == {"code_map", "factorization_histogram"}
    assert all(_is_png(path) for path in paths.values())


def test_plot_functions_accept_plain_arrays(tmp_path) -> None:
    codes = torch.arange(15 * 13).view(15, 13) // 20
    assert _is_png(plot_code_maps(codes, tmp_path / "a.png"))
    assert _is_png(plot_code_maps(np.stack([codes, -codes - 1]), tmp_path / "b.png"))
    assert _is_png(plot_factorization_histogram([[10, 1], [2, 8]], tmp_path / "c.png"))
    env = key_wall()
    without_key, with_key = key_room_code_maps(env, key_wall_oracle())
    assert _is_png(plot_key_room_code_map(env, without_key, with_key, tmp_path / "d" / "e.png"))
    with pytest.raises(ValueError, match="16, 16"):
        plot_key_room_code_map(env, codes, with_key, tmp_path / "f.png")
