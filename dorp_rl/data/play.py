"""Play data: the paper's goal-free exploration, collected with torchrl's ``Collector``."""

from __future__ import annotations

import copy
import json
import math
import shutil
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import Sampler

from dorp_rl.envs.grid_base import GridWorldEnv

#: Keys kept for every transition of the play data.
PLAY_KEYS = (
    "pixels",
    "state",
    "action",
    "step_count",
    "traj_id",
    ("next", "pixels"),
    ("next", "state"),
)
_METADATA_FILE = "play_data.json"
_FORMAT_VERSION = 1


class UniformRandomPolicy:
    """The exploration policy: uniform random discrete actions from its own generator.

    Args:
        num_actions: size of the discrete action space.
        seed: seed of the policy's generator (independent of torch's global RNG).
        device: where actions are created.
    """

    def __init__(self, num_actions: int, seed: int = 0, device: torch.device | str = "cpu") -> None:
        self.num_actions = int(num_actions)
        self.device = torch.device(device)
        self.rng = torch.Generator(device=self.device)
        self.rng.manual_seed(int(seed))

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = torch.randint(
            self.num_actions,
            (*tensordict.batch_size, 1),
            generator=self.rng,
            device=self.device,
        )
        tensordict.set("action", action)
        return tensordict


def play_env(env: GridWorldEnv, trajectory_length: int | None = None) -> GridWorldEnv:
    """A copy of ``env`` set up for play: episodes of ``trajectory_length`` steps, no goal stop.

    Rearrangement play data resets after every step (``trajectory_length=1``); key rooms
    walk 1000 (key-wall) or 1500 (key-corridor) random steps, as in the paper.
    """
    if not isinstance(env, GridWorldEnv):
        raise ValueError(f"env must be a dorp_rl GridWorldEnv, got {type(env).__name__}.")
    length = env.PLAY_TRAJECTORY_LENGTH if trajectory_length is None else int(trajectory_length)
    if length < 1:
        raise ValueError(f"trajectory_length must be >= 1, got {trajectory_length}.")
    if env.batch_size == torch.Size([]) and not env.batch_locked:
        raise ValueError("env must be batch-locked to collect play data (batch_locked=True).")
    out = copy.deepcopy(env)
    out.max_steps = length
    out.terminate_on_success = False
    return out


def _metadata(env: GridWorldEnv, num_frames: int, seed: int, trajectory_length: int) -> dict:
    return {
        "format_version": _FORMAT_VERSION,
        "env_config": env.config(),
        "num_frames": int(num_frames),
        "seed": int(seed),
        "trajectory_length": int(trajectory_length),
        "num_envs": int(env.batch_size.numel()),
    }


def _make_buffer(
    num_frames: int,
    directory: Path | None,
    sampler: Sampler | None,
    batch_size: int | None,
    device: torch.device,
) -> TensorDictReplayBuffer:
    if directory is None:
        storage = LazyTensorStorage(num_frames, device=device)
    else:
        storage = LazyMemmapStorage(num_frames, scratch_dir=directory / "storage")
    kwargs: dict[str, Any] = {"storage": storage, "batch_size": batch_size}
    if sampler is not None:
        kwargs["sampler"] = sampler
    return TensorDictReplayBuffer(**kwargs)


def load_play_data(
    directory: str | Path,
    *,
    sampler: Sampler | None = None,
    batch_size: int | None = None,
    expected: dict | None = None,
) -> TensorDictReplayBuffer:
    """Loads play data written by :func:`collect_play_data` (memory-mapped, no copy).

    Args:
        directory: folder given to :func:`collect_play_data`.
        sampler: sampler of the returned buffer (e.g. :class:`FuturePairSampler`).
        batch_size: default sample size of the returned buffer.
        expected: metadata the data must match (keys of :func:`play_data_metadata`);
            a mismatch raises ``ValueError`` naming the differing entries.
    """
    directory = Path(directory)
    meta_path = directory / _METADATA_FILE
    if not meta_path.exists():
        raise FileNotFoundError(f"no play data at {directory}: {_METADATA_FILE} is missing.")
    try:
        metadata = json.loads(meta_path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"play data metadata {meta_path} is corrupted: {err}.") from err
    required = ("format_version", "env_config", "num_frames", "seed", "trajectory_length")
    if not isinstance(metadata, dict) or any(k not in metadata for k in required):
        raise ValueError(
            f"play data metadata {meta_path} is corrupted: expected a JSON object with {list(required)}."
        )
    if metadata.get("format_version") != _FORMAT_VERSION:
        raise ValueError(
            f"play data at {directory} has format_version {metadata.get('format_version')}, "
            f"expected {_FORMAT_VERSION}."
        )
    if expected is not None:
        diff = {k: (metadata.get(k), v) for k, v in expected.items() if metadata.get(k) != v}
        if diff:
            lines = "; ".join(f"{k}: stored {a!r}, requested {b!r}" for k, (a, b) in diff.items())
            raise ValueError(f"play data at {directory} does not match the request ({lines}).")
    buffer = _make_buffer(
        metadata["num_frames"], directory, sampler, batch_size, torch.device("cpu")
    )
    try:
        buffer.loads(directory)
    except Exception as err:  # a partial or damaged dump
        raise ValueError(f"play data at {directory} could not be loaded ({err}).") from err
    # ReplayBuffer.loads restores the batch size saved at collection time; use the requested one.
    buffer._batch_size = batch_size
    if len(buffer) != metadata["num_frames"]:
        raise ValueError(
            f"play data at {directory} holds {len(buffer)} frames, its metadata says "
            f"{metadata['num_frames']}: the collection was probably interrupted."
        )
    buffer.metadata = metadata
    return buffer


def collect_play_data(
    env: GridWorldEnv,
    num_frames: int,
    *,
    directory: str | Path | None = None,
    seed: int = 0,
    trajectory_length: int | None = None,
    sampler: Sampler | None = None,
    batch_size: int | None = None,
    progress: bool = False,
) -> TensorDictReplayBuffer:
    """Collects ``num_frames`` transitions of random play into a replay buffer.

    Runs the paper's exploration with torchrl's :class:`~torchrl.collectors.Collector`:
    uniform random actions in a copy of ``env`` whose episodes last
    ``trajectory_length`` steps (by default one step for rearrangement, i.e. a fresh
    random configuration per transition, and 1000 / 1500-step random walks for
    key-wall / key-corridor). ``env.batch_size`` copies run side by side.

    Each stored transition holds ``pixels``, ``state``, ``action``, ``step_count`` (the
    step within its trajectory), ``traj_id`` and ``("next", "pixels" | "state")``.

    Args:
        env: a batch-locked :class:`~dorp_rl.envs.GridWorldEnv` (its batch = parallel envs).
        num_frames: transitions to keep.
        directory: if given, data live in a ``LazyMemmapStorage`` there; when the folder
            already holds data collected with the same env, size, seed and trajectory
            length, it is loaded instead of collected again.
        seed: seeds both the env and the exploration policy: same seed, same data.
        trajectory_length: overrides the env's play trajectory length.
        sampler: sampler of the returned buffer (default: uniform over transitions).
        batch_size: default sample size of the returned buffer.
        progress: show a tqdm bar.

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.data import collect_play_data
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(16,))
        >>> buffer = collect_play_data(env, 256, seed=0)
        >>> len(buffer), buffer[0]["pixels"].shape
        (256, torch.Size([3, 16, 16]))
    """
    num_frames = int(num_frames)
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}.")
    collect_env = play_env(env, trajectory_length)
    length = collect_env.max_steps
    metadata = _metadata(collect_env, num_frames, seed, length)
    if directory is not None:
        directory = Path(directory)
        if (directory / _METADATA_FILE).exists():
            check = {
                k: metadata[k] for k in ("env_config", "num_frames", "seed", "trajectory_length")
            }
            return load_play_data(directory, sampler=sampler, batch_size=batch_size, expected=check)
        # No metadata: nothing complete is here. Clear what an interrupted collection left.
        shutil.rmtree(directory / "storage", ignore_errors=True)
        directory.mkdir(parents=True, exist_ok=True)

    num_envs = int(collect_env.batch_size.numel())
    # Whole trajectories per collector batch keep each walk contiguous in storage.
    steps_per_batch = max(1, min(length if length > 1 else 64, math.ceil(num_frames / num_envs)))
    frames_per_batch = num_envs * steps_per_batch
    total_frames = math.ceil(num_frames / frames_per_batch) * frames_per_batch

    collect_env.set_seed(seed)
    policy = UniformRandomPolicy(collect_env.num_actions, seed=seed + 1, device=collect_env.device)
    collector = Collector(
        collect_env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        device=collect_env.device,
        trust_policy=True,
    )
    buffer = _make_buffer(num_frames, directory, sampler, batch_size, collect_env.device)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=num_frames, desc="play data", unit="frame")
    stored = 0
    try:
        for batch in collector:
            batch = batch.reshape(-1)  # env-major: each env's steps stay consecutive
            batch.set("traj_id", batch.get(("collector", "traj_ids")))
            take = min(num_frames - stored, batch.shape[0])
            buffer.extend(batch[:take].select(*PLAY_KEYS).cpu())
            stored += take
            if bar is not None:
                bar.update(take)
            if stored >= num_frames:
                break
    finally:
        collector.shutdown()
        if bar is not None:
            bar.close()
    buffer.metadata = metadata
    if directory is not None:
        buffer.dumps(directory)
        # Written last: its presence marks a complete collection.
        (directory / _METADATA_FILE).write_text(json.dumps(metadata, indent=2))
    return buffer
