"""Frames for people: nearest-neighbour upscaling, rgb arrays and PNG strips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from dorp_rl.frames import check_viewable_frames, frames_to_rgb_array, upscale_frames

__all__ = ["frame_grid", "frames_to_rgb_array", "save_frame_strip", "upscale_frames"]


def frame_grid(frames: torch.Tensor, scale: int = 8, gap: int = 1) -> np.ndarray:
    """Lays out ``[N, 3, H, W]`` (one row) or ``[R, N, 3, H, W]`` frames as one rgb array.

    Frames are separated by ``gap`` grey pixels (in upscaled units) so that black
    backgrounds stay distinguishable.

    Examples:
        >>> import torch
        >>> from dorp_rl.viz import frame_grid
        >>> frames = torch.zeros(2, 4, 3, 16, 16, dtype=torch.uint8)  # 2 rows of 4 frames
        >>> frame_grid(frames, scale=2, gap=1).shape  # 2 * 32 + 3 gaps, 4 * 32 + 5 gaps
        (67, 133, 3)
    """
    frames = check_viewable_frames(frames)
    if frames.dim() == 4:
        frames = frames.unsqueeze(0)
    if frames.dim() != 5:
        raise ValueError(
            f"frames must be [N, 3, H, W] or [R, N, 3, H, W], got {list(frames.shape)}."
        )
    rows, cols, _, height, width = frames.shape
    big = frames_to_rgb_array(frames, scale)  # [R, N, H*s, W*s, 3]
    hs, ws = height * scale, width * scale
    canvas = np.full(
        (rows * hs + (rows + 1) * gap, cols * ws + (cols + 1) * gap, 3), 96, dtype=np.uint8
    )
    for r in range(rows):
        for c in range(cols):
            top, left = gap + r * (hs + gap), gap + c * (ws + gap)
            canvas[top : top + hs, left : left + ws] = big[r, c]
    return canvas


def save_frame_strip(frames: torch.Tensor, path: str | Path, scale: int = 8, gap: int = 1) -> Path:
    """Writes :func:`frame_grid` of ``frames`` to a PNG file and returns its path."""
    image = frame_grid(frames, scale=scale, gap=gap)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
    return path
