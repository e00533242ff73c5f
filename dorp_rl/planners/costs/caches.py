"""Caches the costs keep between planner calls: values by row key (:class:`KeyedCache`)
and an encoder's outputs by frame (:class:`EncodingCache`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from dorp_rl.envs.planning import row_hashes

__all__ = ["EncodingCache", "KeyedCache"]


class KeyedCache:
    """Values of rows already computed, keyed by a 64-bit hash of the rows' bytes.

    Planning calls keep imagining the same few thousand frames around the current state,
    so most model, encoder and cost calls repeat earlier ones. Each entry is a tuple of
    tensor rows (codes and probabilities of a frame; the cost of a (frame, goal) pair).
    Entries are appended to fixed storage of ``size`` rows; a sorted index of their keys
    (looked up with ``searchsorted``) is all that is re-sorted per call, so an insertion
    costs 16 bytes per held entry rather than a copy of every held value. When the
    storage is full the cache starts afresh. It is emptied whenever the weights of the
    module computing the values change (their ``_version`` counters, which every in-place
    update such as an optimiser step increments) and is not part of any state dict. Rows
    are matched by their :func:`~dorp_rl.envs.planning.row_hashes`: two different rows
    share one with probability at most about 2**-56 per pair, and rows found sharing one
    while deduplicating a call are not cached.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.keys = self.slots = None  # sorted keys [n] and their storage rows [n]
        self.values: tuple[torch.Tensor, ...] | None = None  # storage [size, ...] each
        self.count = 0
        self.version: tuple | None = None

    def clear(self) -> None:
        """Forget every entry (the storage is kept for reuse)."""
        self.keys = self.slots = None
        self.count = 0

    def fetch(
        self,
        keys: torch.Tensor,
        compute: Callable[[torch.Tensor], tuple[torch.Tensor, ...]],
        module: nn.Module | None,
    ) -> tuple[torch.Tensor, ...]:
        """The values of the rows of ``keys`` (int64 ``[n]``): held ones from the cache,
        the others from ``compute(indices)`` (the indices into ``keys`` it misses), which
        are then held too."""
        count = keys.shape[0]
        version = (id(module), *(p._version for p in module.parameters())) if module else None
        if version != self.version:
            self.clear()
            self.version = version
        hit = torch.zeros(count, dtype=torch.bool, device=keys.device)
        slot = None
        if self.keys is not None and self.keys.device == keys.device:
            pos = torch.searchsorted(self.keys, keys).clamp_max(self.keys.shape[0] - 1)
            hit = self.keys[pos] == keys
            slot = self.slots[pos]
        miss = (~hit).nonzero().squeeze(-1)
        new = compute(miss) if miss.numel() else None
        if slot is None:
            out = tuple(
                torch.empty(count, *v.shape[1:], dtype=v.dtype, device=v.device) for v in new
            )
        else:
            slot = slot.masked_fill(~hit, 0)
            out = tuple(stored[slot] for stored in self.values)
        if new is not None:
            for target, value in zip(out, new, strict=True):
                target[miss] = value
            self._insert(keys[miss], new)
        return out

    def _insert(self, keys: torch.Tensor, values: tuple[torch.Tensor, ...]) -> None:
        added = keys.shape[0]
        if added > self.size:
            return
        if self.count + added > self.size:
            self.clear()
        if self.values is None or any(
            stored.shape[1:] != v.shape[1:] or stored.dtype != v.dtype or stored.device != v.device
            for stored, v in zip(self.values, values, strict=True)
        ):
            self.clear()
            self.values = tuple(v.new_empty(self.size, *v.shape[1:]) for v in values)
        rows = torch.arange(self.count, self.count + added, device=keys.device)
        for stored, value in zip(self.values, values, strict=True):
            stored[rows] = value
        self.count += added
        if self.keys is not None:
            keys, rows = torch.cat([self.keys, keys]), torch.cat([self.slots, rows])
        order = torch.argsort(keys)
        self.keys, self.slots = keys[order], rows[order]


class EncodingCache(KeyedCache):
    """Codes and probabilities of frames already encoded (a :class:`KeyedCache` of frames)."""

    def encode(self, frames, encode_frames, module: nn.Module | None, keys=None):
        """Codes and probabilities of ``frames``; ``keys``: their row hashes if known.

        ``frames`` may also be a function drawing the uint8 frames of given indices
        (``None``: all), with ``keys`` given: only the frames the cache misses are drawn.
        """
        lazy = not isinstance(frames, torch.Tensor)
        if lazy and (keys is None or self.size == 0):
            frames, lazy = frames(None), False
        if not lazy and (self.size == 0 or frames.dtype != torch.uint8 or frames.shape[0] == 0):
            return encode_frames(frames)
        keys = row_hashes(frames) if keys is None else keys
        return self.fetch(
            keys, lambda miss: encode_frames(frames(miss) if lazy else frames[miss]), module
        )
