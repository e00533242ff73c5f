"""Frames: the checks and conversions of image observations, in one place.

The envs draw, the planners compare and the models read frames ``[*B, C, H, W]``: uint8,
or floats in ``[0, 1]`` where a user gives them. :func:`check_frames` checks a layout,
:func:`frames_to_uint8` / :func:`frames_to_unit_float` convert where frames enter,
:func:`frame_shape_of` reads an env's image spec, :func:`check_task_frames` is the one
check of the frames given to a policy or planner, and :func:`frames_to_rgb_array` /
:func:`upscale_frames` make frames people can look at.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dorp_rl.validation import as_tensor, check_int

__all__ = [
    "check_frames",
    "check_task_frames",
    "check_viewable_frames",
    "frame_shape_of",
    "frames_to_rgb_array",
    "frames_to_uint8",
    "frames_to_unit_float",
    "upscale_frames",
]


def _lead_text(lead: str | Sequence[int]) -> str:
    return lead if isinstance(lead, str) else ", ".join(str(d) for d in lead)


def check_frames(
    pixels: Any,
    name: str = "pixels",
    *,
    floats: bool = False,
    lead: str | Sequence[int] = "*B",
    shape: Sequence[int] | None = None,
) -> torch.Tensor:
    """Checks frames ``[*B, C, H, W]`` and returns them as a tensor (numpy arrays are taken).

    Args:
        pixels: uint8 frames, or floats in ``[0, 1]`` when ``floats`` is set.
        name: the argument's name, for the message.
        floats: also take floating-point frames; their values must lie in ``[0, 1]``
            (one device synchronisation): a float frame in ``0..255`` is a forgotten
            ``/ 255`` and is refused rather than silently misread.
        lead: the leading dimensions: ``"*B"`` or ``"..."`` (any), named ones
            (``"N"``, ``"B, H"``: exactly that many) or a shape.
        shape: the frame shape ``(C, H, W)`` they must have (``None``: any, with at
            least one channel and one pixel).
    """
    pixels = as_tensor(pixels, name)
    if shape is not None:
        shape = tuple(int(d) for d in shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"a frame shape is (C, H, W) with every size >= 1, got {shape}.")
    frame_text = "C, H, W" if shape is None else ", ".join(map(str, shape))
    layout = f"[{_lead_text(lead)}, {frame_text}]"
    if lead in ("*B", "..."):
        lead_ok = pixels.dim() >= 3
    elif isinstance(lead, str):  # named dimensions: "N", "B, H"
        lead_ok = pixels.dim() == 3 + len(lead.split(","))
    else:
        lead_ok = pixels.dim() >= 3 and tuple(pixels.shape[:-3]) == tuple(lead)
    frame_ok = pixels.dim() >= 3 and min(pixels.shape[-3:]) >= 1
    if shape is not None:
        frame_ok = frame_ok and tuple(pixels.shape[-3:]) == shape
    if not (lead_ok and frame_ok):
        raise ValueError(f"{name} must have shape {layout}, got {list(pixels.shape)}.")
    if pixels.dtype == torch.uint8:
        return pixels
    if not floats or not pixels.dtype.is_floating_point:
        allowed = "uint8 (0-255) or floating point (0-1)" if floats else "uint8 (0-255)"
        raise ValueError(f"{name} must be {allowed}, got dtype {pixels.dtype}.")
    if pixels.numel():
        # aminmax propagates NaN: one device synchronisation finds NaN, inf and 0..255.
        values = pixels.detach()
        if values.dtype in (torch.float16, torch.bfloat16):
            values = values.float()
        low, high = torch.stack(torch.aminmax(values)).tolist()
        if math.isnan(low) or math.isnan(high):
            raise ValueError(
                f"{name} hold NaN: float frames must lie in [0, 1] (a frame of NaN is no "
                "image; was it produced by a diverged model?)."
            )
        if not (low >= 0.0 and high <= 1.0):
            raise ValueError(
                f"{name} are floats with values in [{low:g}, {high:g}]: float frames must lie "
                "in [0, 1] (divide uint8 frames by 255, or pass the uint8 frames as they are)."
            )
    return pixels


def frames_to_unit_float(
    pixels: Any, name: str = "pixels", *, shape: Sequence[int] | None = None
) -> torch.Tensor:
    """Frames ``[*B, C, H, W]`` (uint8, or floats of any precision in ``[0, 1]``) as
    float32 in ``[0, 1]`` (the dtype of the models' weights); ``shape`` as in
    :func:`check_frames`."""
    pixels = check_frames(pixels, name, floats=True, shape=shape)
    if pixels.dtype == torch.uint8:
        return pixels.float() / 255.0
    return pixels.to(torch.float32)


def frames_to_uint8(
    pixels: Any,
    name: str = "pixels",
    *,
    lead: str | Sequence[int] = "*B",
    shape: Sequence[int] | None = None,
) -> torch.Tensor:
    """Frames (uint8, or floats of any precision in ``[0, 1]``) as uint8 ``[*B, C, H, W]``.

    Float frames are scaled by 255 and rounded, so ``frames.double() / 255`` gives back
    exactly ``frames``. The envs draw, the planners compare and the palette models read
    uint8 frames: converting where frames enter keeps every path on the same values (a
    float goal compared with uint8 predictions would be off by a factor of 255).
    ``lead`` and ``shape`` as in :func:`check_frames`.
    """
    pixels = check_frames(pixels, name, floats=True, lead=lead, shape=shape)
    if pixels.dtype == torch.uint8:
        return pixels
    return (pixels.to(torch.float32) * 255.0).round_().to(torch.uint8)


def frame_shape_of(env: Any, key: Any = "pixels") -> tuple[int, int, int]:
    """``(C, H, W)`` of the image observation ``key`` of a TorchRL env, from its spec.

    The spec's shape after the env's batch dimensions must be three-dimensional and its
    dtype uint8 or floating point (floats in ``[0, 1]``).

    Raises:
        ValueError: an env without such an observation, naming the keys it has.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.frames import frame_shape_of
        >>> frame_shape_of(KeyWallEnv(batch_size=(2,)))
        (3, 16, 16)
    """
    observation_spec = getattr(env, "full_observation_spec", None)
    if observation_spec is None:
        raise ValueError(f"env must be a TorchRL EnvBase with an observation spec, got {env!r}.")
    keys = list(observation_spec.keys(True, True))
    if key not in keys:
        raise ValueError(
            f"{type(env).__name__} has no image observation {key!r}; its observations are "
            f"{keys}. Name the image key, or rename it with a torchrl RenameTransform."
        )
    spec = observation_spec[key]
    shape = tuple(spec.shape[len(getattr(env, "batch_size", ())) :])
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(
            f"{type(env).__name__}'s {key!r} must be an image [C, H, W] (channels first; "
            f"torchrl's ToTensorImage moves them), its spec has shape {list(shape)}."
        )
    if spec.dtype != torch.uint8 and not spec.dtype.is_floating_point:
        raise ValueError(
            f"{type(env).__name__}'s {key!r} must be uint8 or floats in [0, 1], its spec has "
            f"dtype {spec.dtype}."
        )
    return shape  # type: ignore[return-value]


def check_task_frames(
    pixels: Any,
    name: str,
    env: Any,
    *,
    lead: str | Sequence[int] = "*B",
    spec_key: Any = "pixels",
) -> torch.Tensor:
    """Frames that can belong to ``env``'s task, as uint8 (the one check of frames given to
    a policy or a planner: goal images and current frames).

    In order: the layout and values (:func:`frames_to_uint8`: uint8, or floats of any
    precision in ``[0, 1]``; NaN and float frames in 0..255 are refused); the frame shape
    and dtype of ``env``'s observation spec under ``spec_key`` (else ``"pixels"``); no
    all-black frame (every env draws its objects or its agent, so an empty frame is a
    missing or zeroed image); and, if ``env`` has one, its own ``check_frame(frames, name)``
    (e.g. a grid world refuses frames no valid state of it draws: another environment's,
    another number of objects). Reads the values (a few device synchronisations): call it
    once per public call, never per imagined step.

    Args:
        pixels: frames ``[*B, C, H, W]``.
        name: the argument or key, for the messages.
        env: the env (acting or planning) whose frames these must be.
        lead: the leading dimensions (see :func:`check_frames`).
        spec_key: the observation key whose spec describes these frames.

    Returns:
        the frames as uint8 (the tensor itself when it already is).
    """
    spec = None
    observation_spec = getattr(env, "full_observation_spec", None)
    if observation_spec is not None:
        keys = set(observation_spec.keys(True, True))
        for key in (spec_key, "pixels"):
            if key in keys:
                spec = observation_spec[key]
                break
    frames = frames_to_uint8(pixels, name, lead=lead)
    describe = getattr(env, "describe_world", None)
    owner = describe() if callable(describe) else type(env).__name__
    if spec is not None:
        frame_shape = tuple(spec.shape[len(getattr(env, "batch_size", ())) :])
        if tuple(frames.shape[-3:]) != frame_shape:
            raise ValueError(
                f"{name} must have shape [{_lead_text(lead)}, {', '.join(map(str, frame_shape))}] "
                f"(the frames of {owner}), got {list(frames.shape)}."
            )
        if spec.dtype != torch.uint8:
            raise ValueError(
                f"{name}: {owner} declares {spec.dtype} frames, the planners and policies "
                "take uint8 frames (or floats in [0, 1])."
            )
    if frames.numel():
        flat = frames.reshape(-1, frames.shape[-3:].numel())
        black = flat.amax(-1) == 0
        if bool(black.any()):
            index = black.nonzero()[0].item()
            first = list(torch.unravel_index(torch.tensor(index), frames.shape[:-3]))
            raise ValueError(
                f"{name} holds {int(black.sum())} all-black frame(s) (first at batch index "
                f"{[int(i) for i in first]}): every frame of {owner} shows its objects or "
                "agent on the black background, so an empty frame is a missing or zeroed "
                "image, not a task's."
            )
    check_frame = getattr(env, "check_frame", None)
    if callable(check_frame):
        check_frame(frames, name)
    return frames


def check_viewable_frames(frames: Any, name: str = "frames") -> torch.Tensor:
    """Frames people can look at: uint8 ``[..., 3, H, W]`` (RGB) or ``[..., 1, H, W]`` (gray)."""
    shape = getattr(frames, "shape", None)
    if shape is not None and (len(shape) < 3 or shape[-3] not in (1, 3)):
        raise ValueError(
            f"{name} must have shape [..., 3, H, W] (RGB) or [..., 1, H, W] (gray), got "
            f"{list(shape)}."
        )
    return check_frames(frames, name, lead="...")


def upscale_frames(frames: torch.Tensor, scale: int = 8) -> torch.Tensor:
    """Blows each pixel up to a ``scale x scale`` square: uint8 ``[..., C, H*s, W*s]``
    (``C`` 3 for RGB frames, 1 for gray ones).

    Examples:
        >>> import torch
        >>> from dorp_rl.viz import upscale_frames
        >>> upscale_frames(torch.zeros(2, 3, 16, 16, dtype=torch.uint8), scale=4).shape
        torch.Size([2, 3, 64, 64])
    """
    frames = check_viewable_frames(frames)
    scale = check_int("scale", scale, low=1)
    return frames.repeat_interleave(scale, dim=-2).repeat_interleave(scale, dim=-1)


def frames_to_rgb_array(frames: torch.Tensor, scale: int = 8) -> np.ndarray:
    """Upscaled channel-last numpy image(s), uint8 ``[..., H*s, W*s, 3]`` (gymnasium's
    rgb_array); gray frames ``[..., 1, H, W]`` are shown in three equal channels.

    Examples:
        >>> import torch
        >>> from dorp_rl.viz import frames_to_rgb_array
        >>> frames_to_rgb_array(torch.zeros(3, 16, 16, dtype=torch.uint8)).shape
        (128, 128, 3)
    """
    big = upscale_frames(frames, scale)
    if big.shape[-3] == 1:
        big = big.expand(*big.shape[:-3], 3, *big.shape[-2:])
    return big.movedim(-3, -1).cpu().numpy().copy()
