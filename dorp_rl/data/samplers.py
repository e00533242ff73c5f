"""Samplers over play data: (o_t, o_{t+k}) pairs and H-step windows, within trajectories.

All are torchrl :class:`~torchrl.data.replay_buffers.samplers.Sampler` subclasses that
return a 2-D index ``[B, L]`` of consecutive transitions of one trajectory, so the buffer
hands back a ``[B, L]`` tensordict. A window is valid when all its transitions share a
``traj_id`` and their ``step_count`` increases by one at each position, which holds
whatever order the collector wrote trajectories in. :class:`EventWindowSampler` draws
windows holding a rare event (the key taken and the door opened) more often than
uniform sampling would; events are found in the frames (more cells change) or by a
given function (:func:`rare_code_changes` of a DORP encoder's codes).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from dorp_rl.validation import MissingKeyError, check_float, check_int


def stored_column(storage: Storage, key: str) -> torch.Tensor:
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
                self._check_keys(storage)
                traj = stored_column(storage, self.traj_key)
                step = stored_column(storage, self.step_key)
                last = torch.arange(length - 1, n)
                first = last - (length - 1)
                ok = (traj[first] == traj[last]) & (step[last] - step[first] == length - 1)
                starts = first[ok]
            self._cache[length] = starts
        return self._cache[length]

    def _check_keys(self, storage: Storage) -> None:
        for key in (self.traj_key, self.step_key):
            if key not in storage[:1].keys():
                raise MissingKeyError(
                    f"{type(self).__name__} needs the key {key!r} in the stored data "
                    "(collect_play_data writes 'traj_id' and 'step_count')."
                )

    #: transitions of one trajectory a sample spans (set by subclasses)
    window_length: int = 1

    def longest_run(self, storage: Storage) -> int:
        """Longest run of consecutive stored transitions of one trajectory (0 if empty).

        The longest window this sampler could draw: for error messages, one pass over
        the ``traj_id`` and ``step_count`` columns.
        """
        n = len(storage)
        if n == 0:
            return 0
        self._check_keys(storage)
        traj = stored_column(storage, self.traj_key)
        step = stored_column(storage, self.step_key)
        breaks = ((traj[1:] != traj[:-1]) | (step[1:] - step[:-1] != 1)).nonzero().squeeze(-1)
        edges = torch.cat([torch.tensor([-1]), breaks, torch.tensor([n - 1])])
        return int(edges.diff().max())

    def _too_long(self, storage: Storage, what: str) -> ValueError:
        """The error of a window no stored trajectory holds, with the longest run there is."""
        longest = self.longest_run(storage)
        return ValueError(
            f"{what} needs {self.window_length} consecutive transitions of one trajectory, but "
            f"the longest trajectory among the {len(storage)} stored transitions holds "
            f"{longest}: lower it to at most {longest}, or collect longer trajectories "
            "(collect_play_data(..., trajectory_length=...), and enough num_frames for each "
            "env to store one)."
        )

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
    exists. Sampling raises ``ValueError`` when no stored trajectory is long enough for
    ``max_offset`` (naming the offset and the longest trajectory): pairs would otherwise
    silently come from the shorter offsets only.

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
        self.window_length = max_offset

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        # A trajectory that holds a pair of offset max_offset holds every shorter one.
        if len(self.valid_starts(storage, self.max_offset)) == 0:
            raise self._too_long(
                storage,
                f"FuturePairSampler(min_offset={self.min_offset}, max_offset={self.max_offset}): "
                f"a pair of offset {self.max_offset}",
            )
        offsets = torch.arange(self.min_offset, self.max_offset + 1)
        starts = {int(k): self.valid_starts(storage, int(k)) for k in offsets}
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
        self.window_length = self.horizon

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        starts = self.valid_starts(storage, self.horizon)
        if len(starts) == 0:
            raise self._too_long(
                storage, f"{type(self).__name__}: a window of horizon={self.horizon}"
            )
        first = self._draw(starts, batch_size)
        return first.unsqueeze(-1) + torch.arange(self.horizon), {}


def changed_pixels(
    storage: Storage,
    key: str = "pixels",
    next_key: tuple[str, str] = ("next", "pixels"),
    chunk_size: int = 8192,
) -> torch.Tensor:
    """int64 ``[N]``: per stored transition, the cells whose colour differs between ``key`` and ``next_key``.

    Frames are ``[N, C, H, W]``; a cell counts once whatever number of channels changed.
    Read in chunks of ``chunk_size`` transitions, so memory-mapped play data is never
    loaded whole.
    """
    length = len(storage)
    inner = getattr(storage, "_storage", None)
    source = inner if isinstance(inner, TensorDictBase) else storage[:length]
    for name in (key, next_key):
        if name not in source.keys(include_nested=True):
            raise MissingKeyError(
                f"counting changed pixels needs the key {name!r} in the stored data "
                "(collect_play_data writes 'pixels' and ('next', 'pixels'))."
            )
    out = torch.empty(length, dtype=torch.int64)
    for start in range(0, length, chunk_size):
        stop = min(length, start + chunk_size)
        before = source.get(key)[start:stop]
        after = source.get(next_key)[start:stop]
        out[start:stop] = (before != after).any(-3).flatten(-2).sum(-1).cpu()
    return out


def event_transitions(changed: torch.Tensor, min_changed: int | None = None) -> torch.Tensor:
    """bool ``[N]``: the transitions that change more than an ordinary step does.

    ``changed`` holds the changed cells of each transition (:func:`changed_pixels`). With
    ``min_changed=None`` the ordinary step is read off the data: the most common count
    among the transitions that change anything (in the key rooms an agent move, 2 cells),
    and an event changes more cells than that (the key taken and the door opened: 5).
    Otherwise an event changes at least ``min_changed`` cells.

    Examples:
        >>> import torch
        >>> from dorp_rl.data.samplers import event_transitions
        >>> event_transitions(torch.tensor([2, 0, 2, 5, 2, 2])).tolist()
        [False, False, False, True, False, False]
    """
    if min_changed is None:
        moved = changed[changed > 0]
        if moved.numel() == 0:
            return torch.zeros_like(changed, dtype=torch.bool)
        min_changed = int(torch.bincount(moved).argmax()) + 1
    return changed >= min_changed


def rare_code_changes(
    codes: torch.Tensor, next_codes: torch.Tensor, ratio: float = 0.25
) -> torch.Tensor:
    """bool ``[N]``: the transitions that change the code of a rarely changing one-hot.

    ``codes`` and ``next_codes`` are a DORP encoder's codes ``[N, K]`` of each
    transition's frames. A one-hot is rare when its code changes on at most ``ratio``
    times as many transitions as the most often changing one-hot's (in MiniGrid DoorKey's
    play data the key-and-door one-hot of a trained encoder changes on 1.4% of the
    transitions, the agent's on 7.9%). Events found in the codes need no assumption about
    how many pixels an event changes (a door toggled in MiniGrid changes fewer than an
    agent's move).

    Examples:
        >>> import torch
        >>> from dorp_rl.data import rare_code_changes
        >>> codes = torch.tensor([[0, 0], [1, 0], [2, 0], [3, 0]])
        >>> nxt = torch.tensor([[1, 0], [2, 0], [3, 1], [4, 0]])
        >>> rare_code_changes(codes, nxt, ratio=0.5).tolist()
        [False, False, True, False]
    """
    if codes.shape != next_codes.shape or codes.dim() != 2:
        raise ValueError(
            f"codes and next_codes must both be [N, K], got {list(codes.shape)} and "
            f"{list(next_codes.shape)}."
        )
    ratio = check_float("ratio", ratio, low=0.0, high=1.0)
    changed = codes != next_codes  # [N, K]
    rates = changed.float().mean(0)
    rare = rates <= ratio * rates.max()
    return (changed & rare).any(-1)


class EventWindowSampler(SequenceSampler):
    """A :class:`SequenceSampler` that draws windows holding a rare event more often.

    Random play in the key rooms takes the key (and opens the door) in about 0.1% of its
    transitions, so a world model trained on uniform windows rarely sees it and learns to
    leave the door shut. This sampler finds the *event* transitions in the data alone
    (:func:`event_transitions`: more cells change than in an ordinary step) and draws
    windows that hold one with probability ``max(event_share, natural share)``, the
    others with the rest, each uniformly within its group. Where events are already at
    least ``event_share`` of the windows (in rearrangement, where every action moves a
    block) sampling is uniform; with no event in the data it is uniform with a warning.
    The flags are computed once per storage revision (one pass over the frames).

    Args:
        horizon: window length H (>= 1).
        event_share: least share of drawn windows that hold an event, in [0, 1] (0:
            uniform windows; 1: event windows only, e.g. to evaluate on them).
        min_changed: changed cells that make an event (``None``: read off the data,
            see :func:`event_transitions`).
        events: a function of the storage giving its event transitions, bool ``[N]``,
            instead of counting changed cells (e.g. :func:`rare_code_changes` of a DORP
            encoder's codes, which a latent world model's trainer uses).
        traj_key, step_key: stored keys of trajectory ids and steps within a trajectory.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.data import EventWindowSampler, collect_play_data
        >>> sampler = EventWindowSampler(5, event_share=0.5)
        >>> buffer = collect_play_data(KeyWallEnv(batch_size=(4,)), 4000, seed=0,
        ...                            sampler=sampler, batch_size=64)
        >>> starts, has_event = sampler.window_events(buffer.storage)
        >>> bool(has_event.float().mean() < 0.1), buffer.sample()["action"].shape
        (True, torch.Size([64, 5, 1]))
    """

    def __init__(
        self,
        horizon: int,
        event_share: float,
        min_changed: int | None = None,
        traj_key: str = "traj_id",
        step_key: str = "step_count",
        events: Callable[[Storage], torch.Tensor] | None = None,
    ) -> None:
        super().__init__(horizon, traj_key, step_key)
        self.event_share = check_float("event_share", event_share, low=0.0, high=1.0)
        self.min_changed = check_int("min_changed", min_changed, low=1, optional=True)
        if events is not None and min_changed is not None:
            raise ValueError("give events= or min_changed=, not both (min_changed counts cells).")
        if events is not None and not callable(events):
            raise ValueError(
                f"events must be a function of the storage, got {type(events).__name__}."
            )
        self.events = events
        self._events: tuple[torch.Tensor, torch.Tensor] | None = None
        self._events_tag: tuple | None = None
        self._warned = False

    def transition_events(self, storage: Storage) -> torch.Tensor:
        """bool ``[len(storage)]``: the stored transitions that are events."""
        if self.events is None:
            return event_transitions(changed_pixels(storage), self.min_changed)
        events = torch.as_tensor(self.events(storage))
        if events.dtype != torch.bool or tuple(events.shape) != (len(storage),):
            raise ValueError(
                f"events(storage) must give bool [{len(storage)}] (one flag per stored "
                f"transition), got {events.dtype} {list(events.shape)}."
            )
        return events.cpu()

    def window_events(self, storage: Storage) -> tuple[torch.Tensor, torch.Tensor]:
        """The valid window starts (int64 ``[M]``) and whether each window holds an event (bool ``[M]``)."""
        starts = self.valid_starts(storage, self.horizon)
        if self._events_tag != self._cache_tag or self._events is None:
            events = self.transition_events(storage)
            # an event at transition i lies in the windows starting at i - H + 1 .. i
            counts = torch.cat([torch.zeros(1, dtype=torch.int64), events.long().cumsum(0)])
            has_event = (counts[starts + self.horizon] - counts[starts]) > 0
            self._events, self._events_tag = (starts, has_event), self._cache_tag
        return self._events

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError("Cannot sample from an empty storage.")
        starts, has_event = self.window_events(storage)
        num_events = int(has_event.sum())
        if len(starts) == 0 or num_events in (0, len(starts)):
            if num_events == 0 and len(starts) and self.event_share > 0 and not self._warned:
                warnings.warn(
                    f"EventWindowSampler: none of the {len(starts)} windows holds an event "
                    "(a transition changing more cells than an ordinary step, or one the "
                    "sampler's events function marks); sampling uniform windows.",
                    UserWarning,
                    stacklevel=2,
                )
                self._warned = True
            return super().sample(storage, batch_size)
        share = max(self.event_share, num_events / len(starts))
        event_starts, other_starts = starts[has_event], starts[~has_event]
        pick_event = torch.rand(batch_size, generator=self._rng) < share
        first = torch.empty(batch_size, dtype=torch.int64)
        for group, rows in ((event_starts, pick_event), (other_starts, ~pick_event)):
            count = int(rows.sum())
            if count:
                first[rows] = self._draw(group, count)
        return first.unsqueeze(-1) + torch.arange(self.horizon), {}

    def _empty(self) -> None:
        super()._empty()
        self._events, self._events_tag = None, None


def future_pairs(sample: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unpacks a :class:`FuturePairSampler` sample into (o_t, o_{t+k}, k).

    Returns:
        anchor pixels ``[B, C, H, W]``, future pixels ``[B, C, H, W]``, offsets ``[B]``.
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
