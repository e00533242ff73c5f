"""Open-loop accuracy of world models over 1..H steps: a video prediction model's frames,
a latent world model's codes (and decoded frames)."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from dorp_rl.frames import check_frames, frames_to_unit_float
from dorp_rl.modules.encoder import eval_mode
from dorp_rl.modules.video import VideoPredictionModel


@torch.no_grad()
def open_loop_accuracy(
    model: VideoPredictionModel,
    sequences: TensorDictBase,
    *,
    deterministic: bool = True,
    chunk_size: int = 256,
    generator: torch.Generator | None = None,
) -> dict[str, Any]:
    """Rolls ``model`` open loop from o_t over each window and scores every step.

    A predicted frame is *exact* when it equals the renderer's frame of the true
    configuration, all 3 x 16 x 16 values (the frames in play data are the renderer's).

    Args:
        model: a :class:`~dorp_rl.modules.VideoPredictionModel`.
        sequences: ``[N, H]`` windows of a :class:`~dorp_rl.data.SequenceSampler`:
            ``pixels`` (only ``[:, 0]`` is read), ``action`` ``[N, H, 1]`` and
            ``("next", "pixels")`` ``[N, H, 3, 16, 16]``.
        deterministic: use the prior mean of the latent (the planning mode).
        chunk_size: windows per forward pass.
        generator: random generator for latent draws when not ``deterministic``.

    Returns:
        ``exact_accuracy`` and ``pixel_mse`` (on values in [0, 1]), each a list of H
        floats (step 1..H), ``exact_accuracy_last`` (step H), ``num_sequences`` and
        ``horizon``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import VideoModelConfig, VideoPredictionModel
        >>> palette = torch.tensor([[0, 0, 0], [255, 255, 0]], dtype=torch.uint8)
        >>> model = VideoPredictionModel(4, palette, VideoModelConfig.small())
        >>> frames = torch.zeros(2, 3, 3, 16, 16, dtype=torch.uint8)
        >>> windows = TensorDict(pixels=frames, action=torch.zeros(2, 3, 1, dtype=torch.int64),
        ...                      next=TensorDict(pixels=frames, batch_size=[2, 3]), batch_size=[2, 3])
        >>> len(open_loop_accuracy(model, windows)["exact_accuracy"])
        3
    """
    if sequences.batch_dims != 2:
        raise ValueError(
            f"sequences must be [N, H] windows (a SequenceSampler sample), got batch shape "
            f"{list(sequences.shape)}."
        )
    n, horizon = sequences.shape
    check_frames(
        sequences.get(("next", "pixels")),
        "('next', 'pixels')",
        lead="N, H",
        shape=model.frame_shape,
    )
    device = model.palette.device
    exact = torch.zeros(horizon, dtype=torch.float64)
    squared = torch.zeros(horizon, dtype=torch.float64)
    with eval_mode(model):
        for start in range(0, n, chunk_size):
            window = sequences[start : start + chunk_size]
            first = window[:, 0].get("pixels").to(device)
            actions = window.get("action").to(device)
            pred = model.rollout(first, actions, deterministic=deterministic, generator=generator)
            true = window.get(("next", "pixels")).to(device)
            exact += (pred == true).flatten(2).all(-1).double().sum(0).cpu()
            diff = (pred.float() - true.float()) / 255.0
            squared += diff.pow(2).flatten(2).mean(-1).double().sum(0).cpu()
    exact /= n
    squared /= n
    return {
        "exact_accuracy": exact.tolist(),
        "pixel_mse": squared.tolist(),
        "exact_accuracy_last": float(exact[-1]),
        "num_sequences": n,
        "horizon": horizon,
    }


@torch.no_grad()
def latent_open_loop_accuracy(
    model: Any,
    code_encoder: Any,
    sequences: TensorDictBase,
    *,
    chunk_size: int = 256,
    pixel_tolerance: float = 0.1,
) -> dict[str, Any]:
    """Rolls a latent world model open loop from o_t over each window and scores its codes.

    At each step 1..H the code head's codes are compared with the codes ``code_encoder``
    gives the true frame (every one-hot equal), and, for a model with a decoder, the
    decoded frame with the true frame (the share of values within ``pixel_tolerance`` on
    the [0, 1] scale).

    Args:
        model: a :class:`~dorp_rl.modules.LatentWorldModel`.
        code_encoder: the DORP encoder whose codes the model predicts.
        sequences: ``[N, H]`` windows (``pixels``, ``action``, ``("next", "pixels")``).
        chunk_size: windows per forward pass.
        pixel_tolerance: largest error of a decoded value counted as right.

    Returns:
        ``code_accuracy`` and ``pixel_accuracy`` (``None`` without a decoder): lists of H
        floats (step 1..H); ``code_accuracy_last``, ``num_sequences`` and ``horizon``.
    """
    from dorp_rl.objectives.latent import LatentWorldModelLoss

    if sequences.batch_dims != 2:
        raise ValueError(
            f"sequences must be [N, H] windows (a SequenceSampler sample), got batch shape "
            f"{list(sequences.shape)}."
        )
    n, horizon = sequences.shape
    loss = LatentWorldModelLoss(model, code_encoder)
    right = torch.zeros(horizon)
    pixels_right = torch.zeros(horizon)
    decoder = getattr(model, "frame_decoder", None) is not None
    device = next(iter(model.parameters())).device
    with eval_mode(model):
        for start in range(0, n, chunk_size):
            chunk = sequences[start : start + chunk_size].to(device)
            frames, action = loss._read(chunk)
            latents = loss.rollout(frames, action)[:, 1:]
            truth = loss.target_codes(frames[:, 1:])
            right += (model.codes(latents) == truth).all(-1).float().sum(0).cpu()
            if decoder:
                error = (model.decode(latents) - frames_to_unit_float(frames[:, 1:])).abs()
                pixels_right += (error <= pixel_tolerance).float().flatten(2).mean(-1).sum(0).cpu()
    code_accuracy = (right / n).tolist()
    return {
        "code_accuracy": code_accuracy,
        "code_accuracy_last": code_accuracy[-1],
        "pixel_accuracy": (pixels_right / n).tolist() if decoder else None,
        "num_sequences": n,
        "horizon": horizon,
    }
