"""Tests of the frame helpers for people: upscaling, rgb arrays and PNG strips."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from dorp_rl.viz import frame_grid, frames_to_rgb_array, save_frame_strip, upscale_frames


def random_frames(*shape: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, shape, dtype=torch.uint8, generator=generator)


@pytest.mark.parametrize("scale", [1, 2, 8])
@pytest.mark.parametrize("shape", [(3, 16, 16), (4, 3, 16, 16), (2, 5, 3, 4, 6)])
def test_upscale_frames_turns_each_pixel_into_a_square(shape, scale):
    frames = random_frames(*shape)
    big = upscale_frames(frames, scale)
    *lead, h, w = shape
    assert big.shape == (*lead, h * scale, w * scale)
    assert big.dtype == torch.uint8
    for dy in range(scale):
        for dx in range(scale):
            assert torch.equal(big[..., dy::scale, dx::scale], frames)
    # Same as a Kronecker product with a block of ones.
    ones = np.ones((scale, scale), dtype=np.uint8)
    want = np.kron(frames.numpy().reshape(-1, h, w), ones).reshape(*lead, h * scale, w * scale)
    np.testing.assert_array_equal(big.numpy(), want)


def test_frames_to_rgb_array_is_channel_last():
    frames = random_frames(2, 3, 16, 16)
    rgb = frames_to_rgb_array(frames, 8)
    assert isinstance(rgb, np.ndarray)
    assert rgb.shape == (2, 128, 128, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[:, 3::8, 5::8], frames.permute(0, 2, 3, 1).numpy())
    rgb[...] = 0  # a copy, not a view of the frames
    assert frames.any()


def test_frame_grid_layout():
    frames = random_frames(2, 3, 3, 16, 16)  # 2 rows of 3 frames
    grid = frame_grid(frames, scale=2, gap=1)
    assert grid.shape == (2 * 32 + 3, 3 * 32 + 4, 3)
    assert grid.dtype == np.uint8
    for r in range(2):
        for c in range(3):
            top, left = 1 + r * 33, 1 + c * 33
            want = frames[r, c].repeat_interleave(2, -2).repeat_interleave(2, -1)
            np.testing.assert_array_equal(
                grid[top : top + 32, left : left + 32], want.permute(1, 2, 0).numpy()
            )
    # The gaps are grey, so that black backgrounds stay apart.
    assert (grid[0] == grid[0, 0]).all() and grid[0, 0].tolist() == [96, 96, 96]
    assert (grid[:, 33] == grid[0, 0]).all()


@pytest.mark.parametrize("n", [1, 4])
def test_save_frame_strip_writes_a_png(tmp_path, n):
    frames = random_frames(n, 3, 16, 16, seed=n)
    path = save_frame_strip(frames, tmp_path / "sub" / "strip.png", scale=8, gap=1)
    assert path == tmp_path / "sub" / "strip.png" and path.exists()
    with Image.open(path) as image:
        assert image.format == "PNG"
        assert image.size == (n * 128 + n + 1, 128 + 2)  # (width, height)
        pixels = np.asarray(image.convert("RGB"))
    np.testing.assert_array_equal(pixels, frame_grid(frames, scale=8, gap=1))
    np.testing.assert_array_equal(
        pixels[1:129, 1:129], frames[0].permute(1, 2, 0).numpy().repeat(8, 0).repeat(8, 1)
    )


def test_save_frame_strip_of_env_frames(tmp_path):
    from dorp_rl.envs import ObjectRearrangementEnv

    env = ObjectRearrangementEnv(num_objects=3, batch_size=(5,), seed=0)
    frames = env.reset()["pixels"]
    path = save_frame_strip(frames, str(tmp_path / "env.png"), scale=4)
    with Image.open(path) as image:
        assert image.size == (5 * 64 + 6, 64 + 2)
        pixels = np.asarray(image.convert("RGB"))
    # Blocks keep their colours: each frame shows 3 * 8 cells * 16 upscaled pixels.
    for i in range(5):
        left = 1 + i * 65
        tile = pixels[1:65, left : left + 64]
        assert (tile != 0).any(-1).sum() == 3 * 8 * 16


@pytest.mark.parametrize(
    ("frames", "match"),
    [
        (torch.zeros(2, 3, 16, 16, dtype=torch.float32), "uint8"),
        (torch.zeros(2, 3, 16, 16, dtype=torch.int64), "uint8"),
        (torch.zeros(2, 4, 16, 16, dtype=torch.uint8), r"\[\.\.\., 3, H, W\]"),
        (torch.zeros(2, 16, 16, 3, dtype=torch.uint8), r"\[\.\.\., 3, H, W\]"),
        (torch.zeros(16, 16, dtype=torch.uint8), r"\[\.\.\., 3, H, W\]"),
        ([[0, 1]], "torch.Tensor or a numpy array"),
    ],
    ids=["float32", "int64", "four-channels", "channel-last", "2d", "list"],
)
def test_bad_frames_raise_value_error(frames, match, tmp_path):
    with pytest.raises(ValueError, match=match):
        upscale_frames(frames)
    with pytest.raises(ValueError, match=match):
        frames_to_rgb_array(frames)
    with pytest.raises(ValueError, match=match):
        save_frame_strip(frames, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def test_numpy_frames_are_taken_like_tensors():
    frames = random_frames(2, 3, 16, 16)
    assert np.array_equal(frames_to_rgb_array(frames.numpy()), frames_to_rgb_array(frames))


def test_bad_scale_and_grid_shape_raise_value_error(tmp_path):
    frames = random_frames(2, 3, 16, 16)
    with pytest.raises(ValueError, match="scale must be >= 1"):
        upscale_frames(frames, 0)
    with pytest.raises(ValueError, match=r"\[N, 3, H, W\] or \[R, N, 3, H, W\]"):
        frame_grid(random_frames(3, 16, 16))
    with pytest.raises(ValueError, match=r"\[N, 3, H, W\] or \[R, N, 3, H, W\]"):
        save_frame_strip(random_frames(2, 2, 2, 3, 4, 4), tmp_path / "bad.png")


@pytest.mark.parametrize("module", ["dorp_rl.eval", "dorp_rl.viz", "dorp_rl.envs", "dorp_rl.cli"])
def test_each_package_imports_first_in_a_fresh_interpreter(module):
    # envs must not import viz (viz -> eval -> envs): any of them can be imported first.
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-c", f"import {module}"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
