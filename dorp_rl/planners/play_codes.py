"""The codes of play data, as the code graph and the measures read them: the codes of
every transition (:func:`encode_transitions`), the actions taken (:func:`play_actions`),
an encoder's fingerprint, and the check that an encoder fits the play data's environment
(:func:`check_encoder_fits_play_data`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from dorp_rl.config import config_differences, format_differences
from dorp_rl.modules.encoder import module_device
from dorp_rl.progress import progress_bar
from dorp_rl.validation import check_int

__all__ = [
    "check_encoder_fits_play_data",
    "check_is_encoder",
    "describe_env_config",
    "encode_transitions",
    "encoder_fingerprint",
    "play_actions",
]


def describe_env_config(env_config: Mapping[str, Any]) -> str:
    """An env config, short: its ``env`` (class) and, where it has one, ``num_objects``."""
    name = str(env_config.get("env", "an unnamed environment"))
    if "num_objects" in env_config:
        return f"{name} with num_objects={env_config['num_objects']}"
    return name


def _code_layout_of(
    play: Mapping[str, Any], sizes: tuple[int, ...]
) -> tuple[tuple[int, ...], tuple[int, ...]] | None:
    """The code layout of the env of a play config with ``sizes[0]`` codes a one-hot, as
    its registered profile declares it (:attr:`~dorp_rl.envs.EnvProfile.code_layout`),
    and the same with one code more (the sizes that stay are fixed by the env, such as a
    2-way key bit); ``None``: no profile of that env declares one."""
    from dorp_rl.envs import env_profile, registered_profiles

    for name in registered_profiles():
        profile = env_profile(name)
        env_type = profile.env_type
        if env_type is None or profile.code_layout is None or env_type.__name__ != play.get("env"):
            continue
        count = play.get("num_objects", 1) if profile.counts_objects else 1
        if not isinstance(count, int):
            return None
        size = sizes[0] if sizes else 1
        return tuple(profile.code_layout(size, count)), tuple(profile.code_layout(size + 1, count))
    return None


def _fits(sizes: tuple[int, ...], layout: tuple[int, ...], other: tuple[int, ...]) -> bool:
    """Whether ``sizes`` have the layout's one-hots and its fixed sizes."""
    fixed = [(i, a) for i, (a, b) in enumerate(zip(layout, other, strict=True)) if a == b]
    return len(sizes) == len(layout) and all(sizes[i] == a for i, a in fixed)


def check_encoder_fits_play_data(buffer: Any, encoder: nn.Module) -> None:
    """Refuses an encoder made for another environment than the one of ``buffer``'s play data.

    The play data's environment is the ``env_config`` of ``buffer.metadata``
    (:func:`~dorp_rl.data.collect_play_data`, :func:`~dorp_rl.data.load_play_data`). The
    encoder's code sizes must have the layout that env's profile declares (its
    ``code_layout``: a 1-object encoder's codes of 2-object frames would build a graph of
    nothing), and an encoder that records its environment (an ``env_config`` attribute:
    trained encoders and the oracle do) must record the same one. Buffers without
    metadata (a TensorDict of transitions) are not checked.

    Raises:
        ValueError: naming both environments and how they differ.
    """
    metadata = getattr(buffer, "metadata", None)
    play = metadata.get("env_config") if isinstance(metadata, Mapping) else None
    if not isinstance(play, Mapping):
        return
    sizes = tuple(int(z) for z in encoder.code_sizes)
    layout = _code_layout_of(play, sizes)
    if layout is not None and not _fits(sizes, *layout):
        raise ValueError(
            f"the encoder gives codes of sizes {sizes}, but the play data come from "
            f"{describe_env_config(play)}, whose codes are of the layout {layout[0]} (its profile's "
            "code_layout): use an encoder trained on the play data's environment."
        )
    own = getattr(encoder, "env_config", None)
    if not isinstance(own, Mapping):
        return
    diff = config_differences(dict(own), dict(play))
    if diff:
        raise ValueError(
            f"the encoder was trained on {describe_env_config(own)}, but the play data come "
            f"from {describe_env_config(play)} ({format_differences(diff, 'encoder', 'play data')}"
            "): use an encoder trained on the play data's environment."
        )


def encoder_fingerprint(encoder: nn.Module) -> str:
    """A short hash of an encoder's weights: tells whether a graph was built with it.

    Examples:
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import encoder_fingerprint
        >>> a = DiscreteCodeEncoder(EncoderConfig.small((8,)))
        >>> encoder_fingerprint(a) == encoder_fingerprint(a), len(encoder_fingerprint(a))
        (True, 16)
    """
    digest = hashlib.sha256()
    for name, value in sorted(encoder.state_dict().items()):
        digest.update(name.encode())
        if isinstance(value, torch.Tensor):
            digest.update(str(value.dtype).encode())
            digest.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()[:16]


def encode_transitions(
    buffer: Any, encoder: nn.Module, *, chunk_size: int = 1024, progress: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Codes int64 ``[N, C]`` of both frames of every transition of a play buffer.

    Args:
        buffer: a play buffer (:func:`~dorp_rl.data.collect_play_data`) or a TensorDict
            ``[N]`` holding ``pixels`` and ``("next", "pixels")``.
        encoder: a :class:`~dorp_rl.modules.DiscreteCodeEncoder` (``encode`` and
            ``code_sizes``), run in eval mode.
        chunk_size: transitions encoded at a time (an integer >= 1).
        progress: show a tqdm bar.

    Returns:
        ``(codes, next_codes)``, the codes of ``pixels`` and of ``("next", "pixels")``.

    Raises:
        ValueError: a bad ``chunk_size``, an object that is no encoder, an encoder made
            for another environment than the play data's
            (:func:`check_encoder_fits_play_data`), an empty buffer or missing frames.
    """
    chunk_size = check_int("chunk_size", chunk_size, low=1)
    check_is_encoder(encoder)
    check_encoder_fits_play_data(buffer, encoder)
    storage = getattr(buffer, "storage", None)
    n = len(buffer)
    if n < 1:
        raise ValueError("the play buffer is empty: no transitions to build a graph from.")
    bar = progress_bar(progress, total=n, desc="encode play data", unit="frame")
    codes, next_codes = [], []
    device = module_device(encoder)
    for start in range(0, n, chunk_size):
        index = torch.arange(start, min(n, start + chunk_size))
        chunk = storage[index] if storage is not None else buffer[index]
        for key, out in (("pixels", codes), (("next", "pixels"), next_codes)):
            pixels = chunk.get(key, None)
            if pixels is None:
                raise ValueError(
                    f"the play data has no {key!r}: a graph needs both frames of each "
                    f"transition (keys present: {sorted(map(str, chunk.keys(True, True)))})."
                )
            out.append(encoder.encode(pixels.to(device)).cpu())
        if bar is not None:
            bar.update(index.numel())
    if bar is not None:
        bar.close()
    return torch.cat(codes), torch.cat(next_codes)


def play_actions(buffer: Any, *, chunk_size: int = 65536) -> torch.Tensor | None:
    """The ``action`` of every transition of a play buffer as indices, int64 ``[N]``:
    integer actions ``[N]`` or ``[N, 1]`` as they are, one-hot actions ``[N, A]`` by their
    hot entry (``None`` when the buffer keeps no integer or one-hot actions)."""
    storage = getattr(buffer, "storage", None)
    n = len(buffer)
    parts = []
    for start in range(0, n, chunk_size):
        index = torch.arange(start, min(n, start + chunk_size))
        chunk = storage[index] if storage is not None else buffer[index]
        action = chunk.get("action", None)
        if action is None or action.is_floating_point():
            return None
        action = action.reshape(index.numel(), -1)
        if action.shape[1] != 1:
            if not bool((action.to(torch.int64).sum(-1) == 1).all()):
                return None  # multi-dimensional actions that are not one-hot: not counted
            action = action.to(torch.int64).argmax(-1, keepdim=True)
        parts.append(action[:, 0].to(torch.int64).cpu())
    return torch.cat(parts) if parts else None


def check_is_encoder(encoder: Any) -> None:
    if getattr(encoder, "code_sizes", None) is None or not callable(
        getattr(encoder, "encode", None)
    ):
        raise ValueError(
            f"encoder must have code_sizes and encode() (a DiscreteCodeEncoder), got "
            f"{type(encoder).__name__}."
        )
