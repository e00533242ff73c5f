"""Samplers over play data: (o_t, o_{t+k}) pairs and H-step windows, within trajectories.

Both are torchrl :class:`~torchrl.data.replay_buffers.samplers.Sampler` subclasses that
return a 2-D index ``[B, L]`` of consecutive transitions of one trajectory, so the buffer
hands back a ``[B, L]`` tensordict. A window is valid when all its transitions share a
``traj_id`` and their ``step_count`` increases by one at each position, which holds
whatever order the collector wrote trajectories in.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from dorp_rl.validation import MissingKeyError, check_int


def _column(storage: Storage, key: str) -> torch.Tensor:
    """One column of the stored transitions, without reading the pixels."""
    length = len(storage)
    inner = getattr(storage, "_storage", None)
    if isinstance(inner, TensorDictBase) and key in inner.keys():
        return inner.get(key)[:length].reshape(length, -1)[:, 0].clone()
    return storage[:length][key].reshape(length, -1)[:, 0]


class _WindowSampler(Sampler):
    """Shared machinery: valid window starts per window length, cached per storage revision."""

    def __init__(self, traj_key: str = "traj_id", step_key: str = "step_count") -> None:
        self.traj_key = traj_key
        self.step_key = step_key
        self._cache: dict[int, torch.Tensor] = {}
        self._cache_tag: tuple | None = None

    def valid_starts(self, storage: Storage, length: int) -> torch.Tensor:
        """int64 ``[M]``: storage indices where a window of ``length`` transitions may start."""
        tag = (id(storage), len(storage), getattr(storage, "_mutation_revision", None))
        if tag != self._cache_tag:
            self._cache, self._cache_tag = {}, tag
        if length not in self._cache:
            n = len(storage)
            if n < length:
                starts = torch.empty(0, dtype=torch.int64)
            else:
                for key in (self.traj_key, self.step_key):
                    if key not in storage[:1].keys():
                        raise MissingKeyError(
                            f"{type(self).__name__} needs the key {key!r} in the stored data "
                            "(collect_play_data writes 'traj_id' and 'step_count')."
                        )
                traj = _column(storage, self.traj_key)
                step = _column(storage, self.step_key)
                last = torch.arange(length - 1, n)
                first = last - (length - 1)
                ok = (traj[first] == traj[last]) & (step[last] - step[first] == length - 1)
                starts = first[ok]
            self._cache[length] = starts
        return self._cache[length]

    def _draw(self, starts: torch.Tensor, count: int) -> torch.Tensor:
        pick = torch.randint(len(starts), (count,), generator=self._rng)
        return starts[pick]

    # Stateless apart from the cache: nothing to save.
    def _empty(self) -> None:
        self._cache, self._cache_tag = {}, None

    def dumps(self, path: str | Path) -> None:
        return None

    def loads(self, path: str | Path) -> None:
        return None

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        return None


class FuturePairSampler(_WindowSampler):
    """Samples (o_t, o_{t+k}) pairs, ``k`` uniform in ``[min_offset, max_offset]``.

    The index has shape ``[B, 2]``: column 0 is transition ``t`` (its ``pixels`` is the
    anchor o_t), column 1 is transition ``t + k - 1`` (its ``("next", "pixels")`` is
    o_{t+k}). A pair never crosses a trajectory boundary; the offsets drawn come back as
    ``"offset"`` in the sample. :func:`future_pairs` unpacks a sample.

    With the paper's rearrangement play data (one-step trajectories) only ``k = 1``
    exists; asking for offsets no trajectory is long enough for raises ``ValueError``.

    Args:
        min_offset: smallest ``k`` (>= 1).
        max_offset: largest ``k`` (defaults to ``min_offset``).
        traj_key, step_key: stored keys of trajectory ids and steps within a trajectory.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.data import FuturePairSampler, collect_play_data, future_pairs
        >>> buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 200,
        ...                            sampler=FuturePairSampler(1, 3), batch_size=8)
        >>> anchor, future, offset = future_pairs(buffer.sample())
        >>> anchor.shape, int(offset.min()) >= 1, int(offset.max()) <= 3
        (torch.Size([8, 3, 16, 16]), True, True)
    """

    def __init__(
        self,
        min_offset: int = 1,
        max_offset: int | None = None,
        traj_key: str = "traj_id",
        step_key: str = "step_count",
    ) -> None:
        super().__init__(traj_key, step_key)
        min_offset = check_int("min_offset", min_offset, low=1)
        max_offset = check_int(
            "max_offset", min_offset if max_offset is None else max_offset, low=1
        )
        if max_offset < min_offset:
            raise ValueError(
                f"offsets must satisfy 1 <= min_offset <= max_offset, got "
                f"min_offset={min_offset}, max_offset={max_offset}."
            )
        self.min_offset, self.max_offset = min_offset, max_offset

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        offsets = torch.arange(self.min_offset, self.max_offset + 1)
        starts = {int(k): self.valid_starts(storage, int(k)) for k in offsets}
        usable = torch.tensor([len(starts[int(k)]) > 0 for k in offsets])
        if not usable.any():
            raise ValueError(
                f"no pair with offset in [{self.min_offset}, {self.max_offset}] fits inside a "
                f"trajectory of the {len(storage)} stored transitions (trajectories too short)."
            )
        offsets = offsets[usable]
        k = offsets[torch.randint(len(offsets), (batch_size,), generator=self._rng)]
        first = torch.empty(batch_size, dtype=torch.int64)
        for value in offsets.tolist():
            rows = (k == value).nonzero().squeeze(-1)
            if rows.numel():
                first[rows] = self._draw(starts[value], rows.numel())
        index = torch.stack([first, first + k - 1], dim=-1)
        return index, {"offset": k}


class SequenceSampler(_WindowSampler):
    """Samples windows of ``horizon`` consecutive transitions of one trajectory.

    The index has shape ``[B, horizon]``; in the sample, ``[:, 0]["pixels"]`` is o_t,
    ``["action"]`` holds a_t .. a_{t+H-1} and ``["next", "pixels"]`` o_{t+1} .. o_{t+H},
    the window a video prediction model trains on.

    Args:
        horizon: window length H (>= 1).
        traj_key, step_key: stored keys of trajectory ids and steps within a trajectory.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.data import SequenceSampler, collect_play_data
        >>> buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 200,
        ...                            sampler=SequenceSampler(5), batch_size=4)
        >>> buffer.sample()["action"].shape
        torch.Size([4, 5, 1])
    """

    def __init__(
        self, horizon: int, traj_key: str = "traj_id", step_key: str = "step_count"
    ) -> None:
        super().__init__(traj_key, step_key)
        self.horizon = check_int("horizon", horizon, low=1)

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        starts = self.valid_starts(storage, self.horizon)
        if len(starts) == 0:
            raise ValueError(
                f"no window of {self.horizon} consecutive transitions lies inside one trajectory "
                f"of the {len(storage)} stored ones; collect longer trajectories "
                "(collect_play_data(..., trajectory_length=...)) or lower the horizon."
            )
        first = self._draw(starts, batch_size)
        return first.unsqueeze(-1) + torch.arange(self.horizon), {}


def future_pairs(sample: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unpacks a :class:`FuturePairSampler` sample into (o_t, o_{t+k}, k).

    Returns:
        anchor pixels ``[B, 3, 16, 16]``, future pixels ``[B, 3, 16, 16]``, offsets ``[B]``.
    """
    if sample.batch_dims != 2 or sample.shape[-1] != 2:
        raise ValueError(
            f"expected a [B, 2] sample from FuturePairSampler, got shape {list(sample.shape)}."
        )
    return (
        sample[:, 0].get("pixels"),
        sample[:, 1].get(("next", "pixels")),
        sample[:, 0].get("offset"),
    )
