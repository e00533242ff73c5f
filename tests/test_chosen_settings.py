"""Settings the library chooses from the env (frames and play data), written to the run.

A config built from a bare ``make_env`` leaves the number of one-hots, the map
competition, the exclusivity weight, the maps' stride and the latent model's event share
open; the trainers choose them from a scan of the play frames and the codes, and record
what they chose and why (``chosen.json``, the checkpoint's config).
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict
from tiny_args import tiny_codes
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.checkpoint import load_checkpoint
from dorp_rl.data import choose_play_length, scan_frames
from dorp_rl.data.play import PLAY_WALK_LENGTH
from dorp_rl.trainers import LatentWorldModelConfig, LatentWorldModelTrainer, RepresentationConfig
from dorp_rl.trainers.representation import RepresentationTrainer, choose_code_settings

#: three pieces of one colour that differ only in shape: an L, a bar and a square
SHAPES = [
    torch.tensor([[1, 0], [1, 0], [1, 1]]),
    torch.tensor([[1, 1, 1, 1]]),
    torch.tensor([[1, 1], [1, 1]]),
]


def one_colour_frames(count: int, height: int = 40, width: int = 52, seed: int = 0):
    """uint8 ``[count, 3, height, width]`` frames of the three white pieces in random
    places that never touch (each in its own band of rows)."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.zeros(count, 3, height, width, dtype=torch.uint8)
    band = height // 3
    for i in range(count):
        for k, shape in enumerate(SHAPES):
            h, w = shape.shape
            r = k * band + int(torch.randint(0, band - h, (1,), generator=g))
            c = int(torch.randint(0, width - w, (1,), generator=g))
            frames[i, :, r : r + h, c : c + w] = (shape * 255).to(torch.uint8)
    return frames


def test_scan_counts_pieces_of_one_colour_that_differ_in_shape():
    scan = scan_frames(one_colour_frames(300))
    assert scan.frame_shape == (3, 40, 52)
    assert scan.pieces == 3 and scan.pieces_median == 3
    assert scan.smallest_piece == 1  # the bar is one pixel high
    # Two pieces in a frame: two counted, whatever their colour.
    two = one_colour_frames(300)
    two[:, :, 26:, :] = 0
    assert scan_frames(two).pieces == 2


def test_scan_finds_the_grid_the_pieces_move_on():
    # one-colour pieces placed at any pixel: no grid
    assert scan_frames(one_colour_frames(300)).motion_step == 1
    # the same pieces on a grid of 3-pixel cells (each piece drawn 3 pixels a cell)
    cells = one_colour_frames(300, height=12, width=16)
    grid = cells.repeat_interleave(3, -2).repeat_interleave(3, -1)
    scan = scan_frames(grid)
    assert scan.motion_step == 3 and scan.smallest_piece == 3
    # shifted by one pixel in every frame alike, it is still a grid of 3
    assert scan_frames(torch.roll(grid, 1, -1)).motion_step == 3


def test_scan_counts_the_colours_of_the_pieces():
    assert scan_frames(one_colour_frames(300)).colours == 1
    coloured = one_colour_frames(300)
    coloured[:, 1:, 13:26] = 0  # the middle band's piece red
    scan = scan_frames(coloured)
    assert scan.colours == 2 and scan.pieces == 3 and scan.pieces_share_colours


def test_pieces_of_one_colour_keep_maps_that_show_their_shapes(tmp_path):
    codes = RepresentationTrainer(tiny_codes("counting_pieces:make_large_one_colour_env", tmp_path))
    assert codes.scan.pieces_share_colours and codes.scan.smallest_piece == 4
    # the bar is 4 pixels high: at stride 4 it would be one map cell high, at 1 four
    assert codes.config.encoder.map_stride == 1
    assert "told apart by shape" in codes.chosen["encoder.map_stride"]["why"]


def test_scan_refuses_what_is_not_a_batch_of_frames():
    with pytest.raises(ValueError, match=r"frames \[N, C, H, W\] with N >= 2"):
        scan_frames(torch.zeros(1, 3, 8, 8, dtype=torch.uint8))
    with pytest.raises(ValueError, match="uint8 or floats"):
        scan_frames(torch.zeros(4, 3, 8, 8, dtype=torch.int32))


def test_a_bare_make_env_gets_its_one_hots_counted_and_the_choices_written(tmp_path):
    cfg = tiny_codes("push_blocks:make_env", tmp_path, trajectory_length=5)
    assert cfg.counts_onehots() and cfg.exclusivity_weight is None
    trainer = RepresentationTrainer(cfg)
    # Two blocks move in the play frames: two one-hots, whose maps compete.
    assert trainer.scan.pieces == 2
    assert trainer.config.code_sizes == (32, 32)
    assert trainer.encoder.code_sizes == (32, 32)
    assert trainer.config.encoder.map_competition == "softmax"
    assert trainer.config.exclusivity_weight == 3.0
    assert trainer.config.encoder.map_stride == 1  # 24 x 32 frames keep every pixel
    record = json.loads((tmp_path / "codes" / "chosen.json").read_text())
    assert record["chosen"]["num_onehots"]["value"] == 2
    assert "2 pieces move" in record["chosen"]["num_onehots"]["why"]
    assert record["scan"]["pieces"] == 2
    result = trainer.train()
    assert result["chosen"] == trainer.chosen
    # The checkpoint holds the resolved config: a resume builds the same encoder.
    stored = load_checkpoint(tmp_path / "codes" / "checkpoints" / "last.pt")
    assert stored["config"]["num_onehots"] == 2
    assert stored["config"]["encoder"]["map_competition"] == "softmax"
    again = RepresentationTrainer(cfg.replace(num_steps=6))
    assert again.train(resume=True)["step"] == 6


def test_settings_the_user_gave_are_kept(tmp_path):
    cfg = tiny_codes(
        "push_blocks:make_env",
        tmp_path,
        num_onehots=3,
        exclusivity_weight=0.5,
        encoder={"channels": 4, "mlp_sizes": (16,), "map_competition": "sigmoid"},
    )
    chosen_cfg, chosen = choose_code_settings(cfg.replace(encoder={"map_stride": 1}), None)
    assert chosen_cfg.code_sizes == (32, 32, 32)
    assert chosen_cfg.encoder.map_competition == "sigmoid"
    assert chosen_cfg.exclusivity_weight == 0.5
    assert chosen == {}
    # One-hots to count but no scan: the error says what to give instead.
    with pytest.raises(ValueError, match="num_onehots"):
        choose_code_settings(tiny_codes("push_blocks:make_env", tmp_path), None)


def test_a_training_that_learns_nothing_stops_early_and_says_why(tmp_path, monkeypatch):
    cfg = tiny_codes(
        "push_blocks:make_env",
        tmp_path,
        trajectory_length=5,
        num_onehots=1,
        num_steps=400,
        collapse_check_after=5,
        max_restarts=1,
        log_every=1,
    )
    trainer = RepresentationTrainer(cfg)
    # Every pair shows the same frame: the codes cannot tell pairs apart.
    frame = trainer.buffer[:1]["pixels"][0]

    def still_batch():
        from tensordict import TensorDict

        pixels = frame.expand(cfg.batch_size, *frame.shape).clone()
        return TensorDict(pixels=pixels, future_pixels=pixels.clone(), batch_size=[cfg.batch_size])

    monkeypatch.setattr(trainer, "_batch", still_batch)
    with pytest.warns(RuntimeWarning, match="collapsed in all 2 attempts"):
        result = trainer.train()
    assert result["step"] < 40  # not the 400 steps planned
    assert result["gave_up"] is not None and "num_frames" in result["gave_up"]
    assert math.isclose(result["metrics"]["loss_cpc"], math.log(cfg.batch_size), abs_tol=0.1)


def test_the_latent_model_chooses_its_event_share_from_the_codes(tmp_path):
    codes = RepresentationTrainer(tiny_codes("push_blocks:make_env", tmp_path, num_onehots=2))
    cfg = LatentWorldModelConfig(
        env="push_blocks:make_env",
        num_frames=256,
        eval_frames=128,
        eval_sequences=4,
        num_envs=4,
        horizon=3,
        trajectory_length=4,
        batch_size=4,
        num_steps=2,
        out_dir=str(tmp_path / "latent"),
        progress=False,
        model={"latent_channels": 4, "channels": 4, "hidden": 8, "decoder_hidden": 8},
    )
    assert cfg.event_share is None and cfg.pixel_weight == 10.0 and cfg.soft_targets
    trainer = LatentWorldModelTrainer(cfg, encoder=codes.encoder)
    share = trainer.config.event_share
    assert share in (0.0, 0.25)
    found = bool(trainer.transition_events(trainer.buffer.storage).any())
    assert share == (0.25 if found else 0.0)
    assert trainer.chosen["event_share"]["value"] == share
    trainer.train()


@pytest.mark.parametrize(
    ("env", "objects", "competition", "exclusivity"),
    [
        ("rearrangement", 1, "sigmoid", 0.0),
        ("rearrangement", 2, "softmax", 3.0),
        ("rearrangement", 5, "softmax", 3.0),
        ("key-wall", None, "sigmoid", 0.0),
        ("key-corridor", None, "sigmoid", 0.0),
    ],
)
def test_the_paper_settings_resolve_to_the_presets_they_were_measured_with(
    env, objects, competition, exclusivity
):
    # The profiles no longer set these fields: the defaults choose what they set before.
    cfg, _ = choose_code_settings(RepresentationConfig.for_env(env, objects), None)
    assert cfg.encoder.map_competition == competition
    assert cfg.exclusivity_weight == exclusivity
    assert cfg.encoder.map_stride == 1  # 16 x 16 frames: every pixel
    latent = LatentWorldModelConfig.for_env(env, objects)
    assert (latent.pixel_weight, latent.soft_targets) == (10.0, True)
    model = latent.model
    assert (model.decoder_kind, model.decoder_hidden, model.dynamics_kind) == ("mlp", 1024, "conv")
    assert model.latent_stride == (2 if objects and objects >= 3 else 4)
    assert model.latent_channels == (16 if objects in (3, 4) else 32)


def test_a_static_background_that_is_not_black_is_subtracted(tmp_path):
    frames = one_colour_frames(64)
    # grey walls along the border and a floor of another shade: static, not black
    frames[:, 1, :, :] = torch.where(frames[:, 1] == 0, 40, frames[:, 1])
    frames[:, :, 0, :] = frames[:, :, -1, :] = 128
    scan = scan_frames(frames)
    assert scan.pieces == 3 and not scan.plain_background
    assert scan.background[:, 0, 5].tolist() == [128] * 3 and int(scan.background[1, 10, 10]) == 40
    assert scan_frames(one_colour_frames(64)).plain_background
    cfg = tiny_codes("push_blocks:make_env", tmp_path, num_onehots=3)
    chosen_cfg, chosen = choose_code_settings(cfg, scan)
    assert chosen_cfg.encoder.subtract_background is True
    assert "not black" in chosen["encoder.subtract_background"]["why"]
    # The encoder sees the frame less its background: a frame of background alone is zero.
    from dorp_rl.modules import DiscreteCodeEncoder

    config = chosen_cfg.encoder_config().replace(frame_shape=(3, 40, 52))
    encoder = DiscreteCodeEncoder(config).eval()
    encoder.set_background(scan.background)
    empty = scan.background.expand(2, 3, 40, 52)
    zero_encoder = DiscreteCodeEncoder(config.replace(subtract_background=False)).eval()
    zero_encoder.load_state_dict(
        {k: v for k, v in encoder.state_dict().items() if k != "background"}
    )
    with torch.no_grad():
        torch.testing.assert_close(
            encoder.object_maps(empty), zero_encoder.object_maps(torch.zeros_like(empty))
        )
    with pytest.raises(ValueError, match="subtract_background=True"):
        zero_encoder.set_background(scan.background)


def test_large_frames_train_codes_and_a_latent_model_at_the_chosen_stride(tmp_path):
    codes = RepresentationTrainer(tiny_codes("counting_pieces:make_large_env", tmp_path))
    # 48 x 64 frames of a 12 x 16 grid drawn 4 pixels a cell: maps at the grid's cells (a
    # stride of 3 would leave 16 x 22 cells, each straddling two grid cells)
    assert codes.scan.motion_step == 4
    assert codes.config.encoder.map_stride == 4 and codes.encoder.map_shape == (12, 16)
    assert "grid of 4 pixels" in codes.chosen["encoder.map_stride"]["why"]
    assert codes.scan.colours == 2 and not codes.scan.pieces_share_colours
    assert codes.config.code_sizes == (32, 32)
    codes.train()
    cfg = LatentWorldModelConfig(
        env="counting_pieces:make_large_env",
        num_frames=256,
        eval_frames=128,
        eval_sequences=4,
        num_envs=4,
        horizon=3,
        trajectory_length=4,
        batch_size=4,
        num_steps=2,
        out_dir=str(tmp_path / "latent"),
        progress=False,
        model={"latent_channels": 4, "channels": 4, "hidden": 8, "decoder_hidden": 8},
    )
    latent = LatentWorldModelTrainer(cfg, encoder=codes.encoder)
    # the encoder's stride: the model reads and decodes 12 x 16 frames
    assert latent.config.model.frame_stride == 4
    assert latent.model.model_frame_shape == (3, 12, 16)
    result = latent.train()
    assert len(result["evaluation"]["code_accuracy"]) == 3
    frames = latent.buffer[:2]["pixels"]
    assert latent.model.decode(latent.model.encode(frames)).shape == (2, 3, 48, 64)


class DotEnv(EnvBase):
    """A dot on a 1 x 10 x 12 canvas that moves right or down; its resets start at the top
    left (``random_starts=False``) or anywhere."""

    def __init__(
        self, batch_size=(4,), random_starts: bool = False, seed: int = 0, device=None
    ) -> None:
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        self.random_starts = random_starts
        self.rng = torch.Generator().manual_seed(seed)
        shape = self.batch_size
        self.observation_spec = Composite(
            pixels=Unbounded((*shape, 1, 10, 12), dtype=torch.uint8),
            place=Unbounded((*shape, 2), dtype=torch.int64),
            shape=shape,
        )
        self.action_spec = Categorical(2, shape=(*shape, 1))
        self.reward_spec = Unbounded((*shape, 1))

    def _draw(self, place: torch.Tensor) -> torch.Tensor:
        frames = torch.zeros(*place.shape[:-1], 1, 10, 12, dtype=torch.uint8)
        flat = frames.view(-1, 10, 12)
        for i, (r, c) in enumerate(place.reshape(-1, 2).tolist()):
            flat[i, r, c] = 255
        return frames

    def _reset(self, td=None):
        n = self.batch_size.numel()
        place = torch.zeros(n, 2, dtype=torch.int64)
        if self.random_starts:
            place = torch.stack(
                [
                    torch.randint(0, 10, (n,), generator=self.rng),
                    torch.randint(0, 12, (n,), generator=self.rng),
                ],
                -1,
            )
        place = place.reshape(*self.batch_size, 2)
        return TensorDict(
            pixels=self._draw(place), place=place, done=torch.zeros(*self.batch_size, 1, dtype=torch.bool),
            terminated=torch.zeros(*self.batch_size, 1, dtype=torch.bool), batch_size=self.batch_size,
        )  # fmt: skip

    def _step(self, td):
        move = torch.nn.functional.one_hot(td["action"].reshape(*self.batch_size), 2)
        place = (td["place"] + move).clamp(max=torch.tensor([9, 11]))
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return TensorDict(
            pixels=self._draw(place), place=place, reward=torch.zeros(*self.batch_size, 1),
            done=done, terminated=done.clone(), batch_size=self.batch_size,
        )  # fmt: skip

    def _set_seed(self, seed):
        self.rng.manual_seed(int(seed or 0))


def test_play_walks_from_resets_that_always_start_alike():
    # every reset the same frame: one-step play would never leave the start
    fixed = RepresentationConfig(env="test_chosen_settings:DotEnv")
    length, why = fixed.play_length_choice()
    assert length == PLAY_WALK_LENGTH and "only 1 distinct frame(s) in 16 resets" in why
    assert fixed.play_trajectory_length == PLAY_WALK_LENGTH
    # varied starts: each transition from a fresh reset
    assert choose_play_length(DotEnv((16,), random_starts=True))[0] == 1
    # a length the config or the profile gives is kept, and nothing is chosen
    assert RepresentationConfig(
        env="test_chosen_settings:DotEnv", trajectory_length=7
    ).play_length_choice() == (7, None)
    with pytest.raises(ValueError, match="walk_length must be >= 1"):
        choose_play_length(DotEnv((16,)), walk_length=0)


def test_a_counted_one_hot_too_many_may_code_nothing_without_a_restart(tmp_path):
    # The number of one-hots is a count of moving pieces: one too many may die.
    counted = RepresentationTrainer(
        tiny_codes("push_blocks:make_env", tmp_path, trajectory_length=5, dead_check_frames=3)
    )
    assert counted.surplus_may_die
    one_narrow = {"min_codes_in_batch": 1.0, "max_codes_in_batch": 9.0, "loss_cpc": 2.0}
    hook = counted.collapse_hook
    # restarted while restarts are left (a screening of initialisations) ...
    narrow = hook.collapse_reason(one_narrow, 10**6)
    assert "only 1 code" in narrow and hook.partial(narrow)
    # ... but out of restarts, training goes on instead of giving up
    hook.out_of_restarts(narrow)
    assert counted.gave_up is None
    all_narrow = {"min_codes_in_batch": 1.0, "max_codes_in_batch": 2.0, "loss_cpc": 2.0}
    reason = hook.collapse_reason(all_narrow, 10**6)
    assert "every one-hot uses at most 2" in reason and not hook.partial(reason)
    hook.out_of_restarts(reason)
    assert counted.gave_up is not None
    # Given one-hots are each meant for an object: one that settles on a code is a collapse.
    given = RepresentationTrainer(
        tiny_codes(
            "push_blocks:make_env",
            tmp_path / "given",
            trajectory_length=5,
            dead_check_frames=3,
            encoder={"channels": 4, "mlp_sizes": (16,), "code_sizes": (32, 32)},
        )
    )
    assert not given.surplus_may_die
    narrow = given.collapse_hook.collapse_reason(one_narrow, 10**6)
    assert "only 1 code" in narrow and not given.collapse_hook.partial(narrow)
    # At the end of an attempt: one dead one-hot of a counted set is no reason to restart,
    # one of a given set is; every one-hot of a counted set dead is.
    for trainer, codes, restarts in (
        (counted, [[0, 1], [0, 2], [0, 3]], False),
        (given, [[0, 1], [0, 2], [0, 3]], True),
        (counted, [[0, 1], [0, 1], [0, 1]], True),
    ):
        trainer.play_codes = lambda n, codes=codes: torch.tensor(codes)
        trainer.step = trainer.attempt_start + trainer.config.num_steps
        assert (trainer.dead_hook.reason({}) is not None) is restarts
