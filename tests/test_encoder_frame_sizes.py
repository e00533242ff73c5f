"""DiscreteCodeEncoder on large and odd frame sizes: map strides (EncoderConfig.map_stride)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict

from dorp_rl.modules import (
    DDDPSimilarity,
    DiscreteCodeEncoder,
    EncoderConfig,
    choose_map_stride,
)
from dorp_rl.objectives import CPCLoss
from dorp_rl.objectives.cpc import uncovered_motion

# (frame_shape, map_stride): the chosen strides of 64 and 84 a side, and an odd frame whose
# sides the stride divides in neither direction (partial blocks at the bottom and right).
STRIDED = [((3, 64, 64), 4), ((3, 84, 84), 5), ((3, 30, 45), 4)]


def encoder_for(shape, stride, code_sizes=(8, 8), **overrides) -> DiscreteCodeEncoder:
    overrides.setdefault("map_competition", "sigmoid")  # independent maps, as checked below
    config = EncoderConfig.small(code_sizes, frame_shape=shape, map_stride=stride, **overrides)
    return DiscreteCodeEncoder(config)


@pytest.mark.parametrize(
    ("frame_shape", "stride"),
    [
        ((3, 16, 16), 1),
        ((3, 24, 32), 1),
        ((1, 24, 32), 1),
        ((3, 30, 30), 1),
        ((3, 8, 8), 1),
        ((3, 31, 31), 1),
        ((3, 32, 32), 2),
        ((3, 64, 64), 4),
        ((3, 84, 84), 5),
        ((3, 64, 128), 4),
        ((1, 200, 100), 6),
    ],
)
def test_choose_map_stride_keeps_16_cells_on_the_shorter_side(frame_shape, stride):
    assert choose_map_stride(frame_shape) == stride
    _, height, width = frame_shape
    assert min(height, width) // stride >= 16 or stride == 1
    assert min(height, width) // (stride + 1) < 16


def test_choose_map_stride_is_at_most_the_smallest_object():
    assert choose_map_stride((3, 84, 84), smallest_object=3) == 3
    assert choose_map_stride((3, 84, 84), smallest_object=7) == 5
    assert choose_map_stride((3, 64, 64), smallest_object=1) == 1
    assert choose_map_stride((3, 16, 16), smallest_object=4) == 1


def test_choose_map_stride_fits_the_grid_the_pieces_move_on():
    # a stride the grid's cells fit: a multiple of the step within the bounds ...
    assert choose_map_stride((3, 84, 84), smallest_object=8, motion_step=2) == 4
    assert choose_map_stride((3, 64, 64), smallest_object=4, motion_step=4) == 4
    # ... or the step itself, maps at the grid's resolution (a 12 x 12 grid, 3 pixels a cell)
    assert choose_map_stride((1, 36, 36), smallest_object=3, motion_step=3) == 3
    # not where a piece is smaller than its cell (its shape would be averaged away) ...
    assert choose_map_stride((3, 80, 80), smallest_object=3, motion_step=5) == 3
    # ... nor below 4 cells a side, nor on frames of no grid
    assert choose_map_stride((3, 12, 12), smallest_object=4, motion_step=4) == 1
    assert choose_map_stride((3, 64, 64), motion_step=1) == 4


def test_choose_map_stride_shows_the_shapes_of_pieces_of_one_colour():
    # the smallest piece spans at least 3 map cells
    assert choose_map_stride((1, 36, 36), 3, motion_step=3, shapes_only=True) == 1
    assert choose_map_stride((3, 84, 84), 12, shapes_only=True) == 4
    assert choose_map_stride((3, 84, 84), 12, motion_step=4, shapes_only=True) == 4
    assert choose_map_stride((3, 84, 84), 6, shapes_only=True) == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (((3, 64),), "frame_shape"),
        (((3, 64, 0),), "frame_shape"),
        (((3, 64, 64), 0), "smallest_object"),
        (((3, 64, 64), 4, 0), "motion_step"),
    ],
)
def test_choose_map_stride_refuses_bad_arguments(args, message):
    with pytest.raises(ValueError, match=message):
        choose_map_stride(*args)


def test_map_stride_is_checked():
    with pytest.raises(ValueError, match="map_stride"):
        EncoderConfig.small((8,), map_stride=0)
    with pytest.raises(ValueError, match="map_stride"):
        encoder_for((3, 16, 24), 17)


def test_configs_stored_without_map_stride_get_1():
    stored = EncoderConfig.small((8, 8), frame_shape=(3, 84, 84)).to_dict()
    del stored["map_stride"]
    assert EncoderConfig.from_dict(stored).map_stride == 1


# The state dict of EncoderConfig.small((8, 8)) before map strides existed: stride 1
# must load checkpoints stored by then.
STATE_DICT_SHAPES = {
    "extractor.0.weight": (16, 3, 3, 3),
    "extractor.0.bias": (16,),
    "extractor.1.weight": (16,),
    "extractor.1.bias": (16,),
    "extractor.1.running_mean": (16,),
    "extractor.1.running_var": (16,),
    "extractor.1.num_batches_tracked": (),
    "extractor.3.weight": (16, 16, 3, 3),
    "extractor.3.bias": (16,),
    "extractor.4.weight": (16,),
    "extractor.4.bias": (16,),
    "extractor.4.running_mean": (16,),
    "extractor.4.running_var": (16,),
    "extractor.4.num_batches_tracked": (),
    "extractor.6.weight": (16, 16, 3, 3),
    "extractor.6.bias": (16,),
    "extractor.7.weight": (16,),
    "extractor.7.bias": (16,),
    "extractor.7.running_mean": (16,),
    "extractor.7.running_var": (16,),
    "extractor.7.num_batches_tracked": (),
    "extractor.9.weight": (2, 16, 3, 3),
    "extractor.9.bias": (2,),
    "map_encoder.0.weight": (128, 256),
    "map_encoder.0.bias": (128,),
    "map_encoder.2.weight": (128, 128),
    "map_encoder.2.bias": (128,),
    "map_encoder.3.weight": (128,),
    "map_encoder.3.bias": (128,),
    "map_encoder.5.weight": (8, 128),
    "map_encoder.5.bias": (8,),
}


def test_stride_1_keeps_the_state_dict_of_before():
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8, 8), map_competition="sigmoid"))
    assert encoder.config.map_stride == 1  # chosen for 16 x 16 frames
    shapes = {k: tuple(v.shape) for k, v in encoder.state_dict().items()}
    assert list(shapes) == list(STATE_DICT_SHAPES)
    assert shapes == STATE_DICT_SHAPES
    config = EncoderConfig.small((8, 8), frame_shape=(3, 84, 84), map_stride=1)
    big = DiscreteCodeEncoder(config)
    assert big.map_shape == (84, 84)
    assert big.state_dict()["map_encoder.0.weight"].shape == (128, 84 * 84)
    # Left open, the stride and the competition are chosen from the frames and one-hots.
    chosen = DiscreteCodeEncoder(EncoderConfig.small((8, 8), frame_shape=(3, 84, 84)))
    assert (chosen.map_stride, chosen.map_shape) == (5, (17, 17))
    assert chosen.config.map_competition == "softmax"  # two object one-hots compete
    assert DiscreteCodeEncoder(EncoderConfig.small((8, 2))).config.map_competition == "sigmoid"


def test_a_stride_only_changes_the_map_encoders_input_width():
    plain = encoder_for((3, 84, 84), 1).state_dict()
    strided = encoder_for((3, 84, 84), 5).state_dict()
    assert list(plain) == list(strided)
    for key, value in plain.items():
        if key != "map_encoder.0.weight":
            assert strided[key].shape == value.shape, key
    assert strided["map_encoder.0.weight"].shape == (128, 17 * 17)


@pytest.mark.parametrize(("frame_shape", "stride"), STRIDED)
def test_strided_codes_and_maps_have_the_right_shapes(frame_shape, stride):
    encoder = encoder_for(frame_shape, stride, code_sizes=(8, 2))
    cells = tuple(math.ceil(d / stride) for d in frame_shape[1:])
    assert encoder.map_shape == cells
    pixels = torch.randint(0, 256, (2, 3, *frame_shape), dtype=torch.uint8)
    code, probs = encoder(pixels)
    assert code.shape == (2, 3, 2) and probs.shape == (2, 3, 2, 8)
    assert bool((code[..., 1] < 2).all())
    logits, maps = encoder.logits_and_maps(pixels)
    assert logits.shape == (2, 3, 2, 8) and maps.shape == (2, 3, 2, *cells)
    assert encoder.encode(pixels).shape == (2, 3, 2)


@pytest.mark.parametrize(("frame_shape", "stride"), STRIDED)
def test_strided_maps_are_the_extractor_on_block_means(frame_shape, stride):
    torch.manual_seed(0)
    encoder = encoder_for(frame_shape, stride).eval()
    encoder.fast_inference = False
    pixels = torch.randint(0, 256, (3, *frame_shape), dtype=torch.uint8)
    x = pixels.float() / 255
    height, width = frame_shape[1:]
    cells = encoder.map_shape
    # pad to whole blocks; each block's mean over the pixels it really has
    padded = F.pad(x, (0, cells[1] * stride - width, 0, cells[0] * stride - height))
    ones = F.pad(
        torch.ones(1, 1, height, width),
        (0, cells[1] * stride - width, 0, cells[0] * stride - height),
    )
    blocks = F.avg_pool2d(padded, stride) / F.avg_pool2d(ones, stride)
    with torch.no_grad():
        expected = encoder.extractor(blocks * encoder.config.input_scale).sigmoid()
        maps = encoder.object_maps(pixels)
    torch.testing.assert_close(maps, expected, rtol=1e-5, atol=1e-5)
    pooled = encoder.pool_to_maps(torch.ones(1, 1, height, width), reduce="sum")
    assert float(pooled.sum()) == height * width
    assert float(pooled.max()) == stride * stride


def toy_batch(frame_shape, count: int, generator: torch.Generator):
    """Frames with one 8 x 8 white square at one of 4 places; the place is the label."""
    _, height, width = frame_shape
    corners = [(2, 3), (2, width - 11), (height - 10, 3), (height - 10, width - 11)]
    labels = torch.randint(0, len(corners), (count,), generator=generator)
    frames = torch.zeros(count, *frame_shape, dtype=torch.uint8)
    for i, label in enumerate(labels.tolist()):
        top, left = corners[label]
        frames[i, :, top : top + 8, left : left + 8] = 255
    return frames, labels


@pytest.mark.parametrize(("frame_shape", "stride"), STRIDED)
def test_a_strided_encoder_learns_a_toy_and_its_inference_extractor_agrees(frame_shape, stride):
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(0)
    encoder = encoder_for(frame_shape, stride, code_sizes=(8,))
    optimizer = torch.optim.Adam(encoder.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        frames, labels = toy_batch(frame_shape, 32, generator)
        loss = F.cross_entropy(encoder.logits(frames)[:, 0], labels)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert sum(losses[-3:]) / 3 < 0.5 * losses[0], losses

    # eval mode: the folded, channels-last extractor against the plain one
    encoder.eval()
    frames, labels = toy_batch(frame_shape, 64, generator)
    frames[:32] = torch.randint(0, 256, (32, *frame_shape), dtype=torch.uint8)
    with torch.no_grad():
        fast = encoder.object_maps(frames)
        encoder.fast_inference = False
        plain = encoder.object_maps(frames)
        plain_codes = encoder(frames)[0]
        encoder.fast_inference = True
        fast_codes = encoder(frames)[0]
    assert fast.shape == (64, 1, *encoder.map_shape)
    torch.testing.assert_close(fast, plain, rtol=1e-4, atol=1e-5)
    assert torch.equal(fast_codes, plain_codes)
    assert float((fast_codes[32:, 0] == encoder.encode(frames[32:])[:, 0]).float().mean()) == 1.0


def test_uncovered_motion_with_a_stride_is_the_full_resolution_share():
    """A pixel takes its map cell's value: the strided term equals the full-resolution
    term on maps upsampled to pixels (each cell repeated over its block, cropped)."""
    torch.manual_seed(0)
    stride, height, width = 4, 30, 45
    cells = (math.ceil(height / stride), math.ceil(width / stride))
    anchor = torch.randint(0, 2, (5, 3, height, width), dtype=torch.uint8)
    future = anchor.clone()
    future[:, :, 10:17, 20:41] = 1 - future[:, :, 10:17, 20:41]
    future[:, :, 28:, 43:] = 7  # the partial corner block
    anchor_maps = torch.rand(5, 2, *cells)
    future_maps = torch.rand(5, 2, *cells)

    def upsample(maps):
        full = maps.repeat_interleave(stride, -2).repeat_interleave(stride, -1)
        return full[..., :height, :width]

    strided = uncovered_motion(anchor, future, anchor_maps, future_maps, stride=stride)
    full = uncovered_motion(anchor, future, upsample(anchor_maps), upsample(future_maps))
    torch.testing.assert_close(strided, full)
    ones = torch.ones(5, 2, *cells)
    assert float(uncovered_motion(anchor, future, ones, ones, stride=stride)) == 0.0
    with pytest.raises(ValueError, match="cells"):
        uncovered_motion(anchor, future, anchor_maps, future_maps, stride=3)


def test_the_cpc_loss_with_every_map_term_trains_a_strided_encoder():
    torch.manual_seed(0)
    encoder = encoder_for((3, 30, 45), 4, code_sizes=(8, 8))
    loss = CPCLoss(
        encoder,
        DDDPSimilarity(16),
        exclusivity_weight=3.0,
        sparsity_weight=5.0,
        motion_weight=1.0,
    )
    pixels = torch.randint(0, 256, (8, 3, 30, 45), dtype=torch.uint8)
    future = pixels.clone()
    future[:, :, :8, :8] = 0
    out = loss(TensorDict(pixels=pixels, future_pixels=future, batch_size=[8]))
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    total.backward()
    assert {"loss_cpc", "loss_exclusivity", "loss_sparsity", "loss_motion"} <= set(out.keys())
    assert encoder.extractor[0].weight.grad.abs().sum() > 0


def test_a_stride_on_upscaled_frames_is_the_small_frames_encoder():
    """Frames drawn with s x s pixels per cell, at stride s, give exactly the codes and
    maps of the 1-pixel-per-cell frames at stride 1 with the same weights."""
    torch.manual_seed(0)
    small = encoder_for((3, 16, 16), 1)
    big = encoder_for((3, 64, 64), 4)
    big.load_state_dict(small.state_dict())
    pixels = torch.randint(0, 256, (6, 3, 16, 16), dtype=torch.uint8)
    upscaled = pixels.repeat_interleave(4, -2).repeat_interleave(4, -1)
    logits, maps = small.logits_and_maps(pixels)
    big_logits, big_maps = big.logits_and_maps(upscaled)
    torch.testing.assert_close(big_maps, maps)
    torch.testing.assert_close(big_logits, logits)
    small.eval()
    big.eval()
    assert torch.equal(big.encode(upscaled), small.encode(pixels))
