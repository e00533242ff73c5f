"""Rollouts as animated GIFs: each frame beside the goal image and DORP's current waypoint.

One GIF frame per env step, three panels side by side:

- the current frame and the goal image (upscaled with
  :func:`~dorp_rl.envs.grid_base.frames_to_rgb_array`, the renderer the envs use);
- the waypoint: DORP's mode (and the group it moves), then one tile per one-hot with its
  current code and the waypoint's (``subgoal_code``). Tiles of the one-hots the waypoint
  concerns (``subgoal_mask``) have a yellow border. Where code maps are given (the maps
  of :mod:`dorp_rl.viz.code_maps`, in the same colours), a tile shows the one-hot's map
  with the waypoint code's cells in colour and every other cell faded, so the region the
  policy is heading for can be seen; otherwise only the code numbers.

The keys read from a rollout are those :class:`~dorp_rl.policies.AbstractGoalPolicy`
writes; a rollout without them (any other policy) gets the two frame panels only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from tensordict import TensorDictBase

from dorp_rl.frames import frames_to_rgb_array
from dorp_rl.viz.code_maps import code_colours

__all__ = [
    "code_maps_for_waypoints",
    "rollout_gif_frames",
    "save_rollout_gif",
    "waypoint_panel",
]

_BACKGROUND = (40, 40, 40)
_TEXT = (235, 235, 235)
_MASKED = (255, 210, 0)  # border of the one-hots in subgoal_mask
_UNMASKED = (110, 110, 110)
_MODE_NAMES = {0: "new", 1: "waypoint", 2: "goal image", 3: "failed", 4: "done"}
_MAP_CELL = 6  # pixels per code-map cell
_TILE_TEXT = 22  # pixels of the two text lines above a tile's maps
_HEADER = 30


def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default()


def code_maps_for_waypoints(
    diagnostics: Mapping[str, Any] | Sequence[Any], num_onehots: int
) -> list[list[np.ndarray] | None]:
    """Per one-hot the code maps to draw in its waypoint tile (``None``: numbers only).

    Args:
        diagnostics: the dict of
            :func:`~dorp_rl.envs.rearrangement_diagnostics` (its
            ``code_maps``), of :func:`~dorp_rl.envs.key_room_diagnostics`
            (the agent one-hot gets its maps without and with the key), or a list of
            per-one-hot maps (``[rows, cols]`` ints, ``None`` for none), as
            :func:`~dorp_rl.envs.rearrangement_code_maps` returns.
        num_onehots: C, the one-hots of the codes.

    Returns:
        A list of length C; each entry a list of int ``[rows, cols]`` maps (``-1``: no
        code) or ``None``.
    """
    maps: list[list[np.ndarray] | None] = [None] * num_onehots
    if isinstance(diagnostics, Mapping):
        if "code_map_with_key" in diagnostics:
            agent = diagnostics["agent_onehot"]
            if 0 <= agent < num_onehots:
                maps[agent] = [
                    np.asarray(diagnostics["code_map_without_key"], dtype=np.int64),
                    np.asarray(diagnostics["code_map_with_key"], dtype=np.int64),
                ]
            return maps
        diagnostics = diagnostics.get("code_maps") or []
    for c, code_map in enumerate(list(diagnostics)[:num_onehots]):
        if code_map is not None:
            array = (
                code_map.detach().cpu().numpy()
                if isinstance(code_map, torch.Tensor)
                else np.asarray(code_map)
            )
            if array.ndim != 2:
                raise ValueError(f"code map {c} must be [rows, cols], got {list(array.shape)}.")
            maps[c] = [array.astype(np.int64)]
    return maps


def _highlighted_map(code_map: np.ndarray, code: int) -> np.ndarray:
    """uint8 ``[rows*s, cols*s, 3]``: cells of ``code`` in their colour, the rest faded."""
    rgb = code_colours(code_map)
    faded = code_map != code
    rgb[faded] = 0.25 * rgb[faded] + 0.75 * np.array([0.15, 0.15, 0.15])
    image = (rgb * 255).round().astype(np.uint8)
    return image.repeat(_MAP_CELL, 0).repeat(_MAP_CELL, 1)


def waypoint_panel(
    code: Sequence[int] | None,
    subgoal_code: Sequence[int],
    subgoal_mask: Sequence[bool],
    mode: int,
    group: int | None = None,
    code_maps: Sequence[Sequence[np.ndarray] | None] | None = None,
) -> np.ndarray:
    """DORP's current waypoint as a picture: uint8 ``[H, W, 3]``.

    Args:
        code: ``[C]`` codes of the current frame (``None``: not shown).
        subgoal_code: ``[C]`` the waypoint.
        subgoal_mask: ``[C]`` the one-hots the waypoint concerns (yellow border).
        mode: ``dorp_mode`` (0 new, 1 waypoint, 2 goal image, 3 failed, 4 done).
        group: ``dorp_group``, shown in waypoint mode.
        code_maps: from :func:`code_maps_for_waypoints`.

    Examples:
        >>> import numpy as np
        >>> from dorp_rl.viz import waypoint_panel
        >>> code_map = np.array([[0, 0, 1], [1, 2, 2]])  # one-hot 0's codes over positions
        >>> panel = waypoint_panel([0, 3], [1, 3], [True, False], 1, 0, [[code_map], None])
        >>> panel.dtype, panel.shape[-1], bool((panel == (255, 210, 0)).all(-1).any())
        (dtype('uint8'), 3, True)
    """
    subgoal = [int(v) for v in subgoal_code]
    mask = [bool(v) for v in subgoal_mask]
    if len(mask) != len(subgoal):
        raise ValueError(
            f"subgoal_mask has {len(mask)} one-hots but subgoal_code has {len(subgoal)}."
        )
    num = len(subgoal)
    maps = list(code_maps) if code_maps is not None else [None] * num
    if len(maps) != num:
        raise ValueError(f"code_maps must have one entry per one-hot ({num}), got {len(maps)}.")
    tiles: list[np.ndarray] = []
    font = _font()
    for c in range(num):
        images = [_highlighted_map(m, subgoal[c]) for m in (maps[c] or [])]
        width = max(64, sum(i.shape[1] + 2 for i in images) + 2)
        height = _TILE_TEXT + (max(i.shape[0] for i in images) + 2 if images else 0) + 4
        tile = Image.new("RGB", (width + 6, height + 6), _MASKED if mask[c] else _UNMASKED)
        inner = Image.new("RGB", (width, height), _BACKGROUND)
        draw = ImageDraw.Draw(inner)
        draw.text((2, 0), f"one-hot {c}", fill=_TEXT, font=font)
        now = "" if code is None else f"{int(code[c])} -> "
        draw.text((2, 10), f"{now}{subgoal[c]}", fill=_MASKED if mask[c] else _TEXT, font=font)
        left = 2
        for image in images:
            inner.paste(Image.fromarray(image), (left, _TILE_TEXT))
            left += image.shape[1] + 2
        tile.paste(inner, (3, 3))
        tiles.append(np.asarray(tile))
    columns = min(num, 3) if num else 1
    rows = [tiles[i : i + columns] for i in range(0, num, columns)]
    row_heights = [max(t.shape[0] for t in row) for row in rows]
    col_widths = [max(row[j].shape[1] for row in rows if j < len(row)) for j in range(columns)] or [
        64
    ]
    width = max(sum(col_widths) + 4 * (columns + 1), 140)
    height = _HEADER + sum(row_heights) + 4 * (len(rows) + 1)
    panel = Image.new("RGB", (width, height), _BACKGROUND)
    draw = ImageDraw.Draw(panel)
    name = _MODE_NAMES.get(int(mode), str(int(mode)))
    draw.text((4, 2), f"DORP: {name}", fill=_TEXT, font=font)
    if group is not None and int(mode) == 1:
        draw.text((4, 14), f"moving group {int(group)}", fill=_TEXT, font=font)
    top = _HEADER + 4
    for row, row_height in zip(rows, row_heights, strict=True):
        left = 4
        for j, tile in enumerate(row):
            panel.paste(Image.fromarray(tile), (left, top))
            left += col_widths[j] + 4
        top += row_height + 4
    return np.asarray(panel)


def _stack(panels: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    """Panels side by side on a common background, vertically centred."""
    height = max(p.shape[0] for p in panels)
    width = sum(p.shape[1] for p in panels) + gap * (len(panels) + 1)
    canvas = np.empty((height + 2 * gap, width, 3), dtype=np.uint8)
    canvas[:] = _BACKGROUND
    left = gap
    for p in panels:
        top = gap + (height - p.shape[0]) // 2
        canvas[top : top + p.shape[0], left : left + p.shape[1]] = p
        left += p.shape[1] + gap
    return canvas


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with a caption line above it."""
    out = Image.new("RGB", (image.shape[1], image.shape[0] + 14), _BACKGROUND)
    out.paste(Image.fromarray(image), (0, 14))
    ImageDraw.Draw(out).text((2, 1), text, fill=_TEXT, font=_font())
    return np.asarray(out)


def _value(rollout: TensorDictBase, key: str, t: int) -> torch.Tensor | None:
    if key not in rollout.keys():
        return None
    return rollout.get(key)[t]


def rollout_gif_frames(
    rollout: TensorDictBase,
    code_maps: Sequence[Sequence[np.ndarray] | None] | None = None,
    *,
    scale: int = 8,
    max_frames: int = 150,
) -> list[np.ndarray]:
    """The GIF frames of one env's rollout: uint8 ``[H, W, 3]`` each.

    Args:
        rollout: one env's ``env.rollout`` output, ``[T]``, with ``pixels`` and
            ``goal_pixels`` (and ``("next", "pixels")`` for the last frame); DORP's
            ``subgoal_code``, ``subgoal_mask``, ``dorp_mode``, ``dorp_group`` and
            ``code`` when present.
        code_maps: per one-hot maps for the waypoint tiles (:func:`code_maps_for_waypoints`).
        scale: upscaling of the 16x16 frames.
        max_frames: at most this many frames (evenly spaced steps; the first and the last
            are kept).

    Returns:
        One rgb array per kept step, plus the frame reached after the last step.
    """
    if rollout.batch_dims != 1:
        raise ValueError(
            f"rollout must be one env's [T] rollout, got batch_size {list(rollout.batch_size)}."
        )
    for key in ("pixels", "goal_pixels"):
        if key not in rollout.keys():
            raise ValueError(f"rollout must hold {key!r}, got {sorted(map(str, rollout.keys()))}.")
    if max_frames < 2:
        raise ValueError(f"max_frames must be >= 2, got {max_frames}.")
    steps = rollout.shape[0]
    pixels = rollout["pixels"]
    if ("next", "pixels") in rollout.keys(True):
        pixels = torch.cat([pixels, rollout["next", "pixels"][-1:]])
    frames = frames_to_rgb_array(pixels, scale)  # [T+1, H*s, W*s, 3]
    goals = frames_to_rgb_array(rollout["goal_pixels"], scale)
    keep = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), max_frames)).round())
    dorp = "subgoal_code" in rollout.keys()
    out: list[np.ndarray] = []
    for t in keep.astype(int).tolist():
        s = min(t, steps - 1)  # the frame after the last step shows the last step's plan
        panels = [_label(frames[t], f"step {t}"), _label(goals[s], "goal")]
        if dorp:
            code = _value(rollout, "code", s)
            mode = _value(rollout, "dorp_mode", s)
            group = _value(rollout, "dorp_group", s)
            mask = _value(rollout, "subgoal_mask", s)
            subgoal = rollout["subgoal_code"][s]
            panels.append(
                waypoint_panel(
                    None if code is None else code.tolist(),
                    subgoal.tolist(),
                    [True] * len(subgoal) if mask is None else mask.tolist(),
                    1 if mode is None else int(mode.reshape(-1)[0]),
                    None if group is None else int(group.reshape(-1)[0]),
                    code_maps,
                )
            )
        out.append(_stack(panels))
    # Every frame the size of the largest (panels may differ in height).
    height = max(f.shape[0] for f in out)
    width = max(f.shape[1] for f in out)
    padded = []
    for f in out:
        canvas = np.empty((height, width, 3), dtype=np.uint8)
        canvas[:] = _BACKGROUND
        canvas[: f.shape[0], : f.shape[1]] = f
        padded.append(canvas)
    return padded


def save_rollout_gif(
    rollout: TensorDictBase,
    path: str | Path,
    code_maps: Sequence[Sequence[np.ndarray] | None] | None = None,
    *,
    scale: int = 8,
    max_frames: int = 150,
    frame_ms: int = 150,
) -> Path:
    """Writes :func:`rollout_gif_frames` of ``rollout`` as an animated GIF (Pillow).

    The last frame is held 5 times longer. Returns ``path`` as a :class:`~pathlib.Path`.
    """
    frames = rollout_gif_frames(rollout, code_maps, scale=scale, max_frames=max_frames)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    durations = [frame_ms] * (len(images) - 1) + [frame_ms * 5]
    images[0].save(
        path,
        save_all=True,
        append_images=images[1:],
        duration=durations,
        loop=0,
        optimize=False,
    )
    return path
