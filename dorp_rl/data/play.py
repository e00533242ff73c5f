"""Play data: the paper's goal-free exploration, collected with torchrl's ``Collector``.

On disk (``collect_play_data(..., directory=...)``) a collection is a folder holding

- ``storage/``: the transitions as memory-mapped tensors (tensordict's layout);
- ``play_data.json``: what was collected (every argument that changes the data), the
  dtype and shape of every stored tensor, and the size and SHA-256 checksum of every
  file under ``storage/``, written last: its presence marks a complete collection;
- ``play_data.lock``: locked while a process writes here, so that two collections
  never mix their data; it also marks ``storage/`` as written by this library.

Loading checks the checksums before any tensor is mapped and maps the files
copy-on-write: loading never writes to the data, and changing a loaded buffer never
reaches the disk.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import warnings
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.envs import EnvBase, StepCounter, TransformedEnv

from dorp_rl.config import config_differences, format_differences
from dorp_rl.envs.spec import DiscreteActions, env_device, env_identity
from dorp_rl.frames import frame_shape_of
from dorp_rl.integrity import (
    DirectoryLock,
    IntegrityError,
    atomic_write_bytes,
    file_manifest,
    verify_manifest,
)
from dorp_rl.progress import progress_bar
from dorp_rl.validation import check_device, check_int, check_seed, derive_seed

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
_LOCK_FILE = "play_data.lock"
_STORAGE = "storage"
#: 2: checksums of every file and of the metadata. 1 (read with a warning): no checksums.
_FORMAT_VERSION = 2
#: Every argument that changes the collected data; a stored collection is reused only
#: when all of them match the request.
MATCH_FIELDS = ("env_config", "num_frames", "seed", "trajectory_length", "num_envs", "device")


class UniformRandomPolicy:
    """The exploration policy: uniform random discrete actions from its own generator.

    Args:
        num_actions: size of the discrete action space.
        seed: seed of the policy's generator (independent of torch's global RNG).
        device: where actions are created.
        actions: the env's action layout (:class:`~dorp_rl.envs.spec.DiscreteActions`:
            key, index or one-hot); default ``"action"``, int64 indices ``[*B, 1]``.
            :meth:`for_env` reads it off an env.

    Examples:
        >>> from dorp_rl.data import UniformRandomPolicy
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(4,), seed=0)
        >>> action = UniformRandomPolicy(env.num_actions, seed=0)(env.reset())["action"]
        >>> action.shape, action.dtype, 0 <= int(action.min()) <= int(action.max()) < 8
        (torch.Size([4, 1]), torch.int64, True)
    """

    def __init__(
        self,
        num_actions: int,
        seed: int = 0,
        device: torch.device | str = "cpu",
        actions: DiscreteActions | None = None,
    ) -> None:
        self.num_actions = check_int("num_actions", num_actions, low=1)
        self.device = check_device(device)
        if actions is None:
            actions = DiscreteActions("action", self.num_actions, False, (1,), torch.int64)
        elif actions.num_actions != self.num_actions:
            raise ValueError(
                f"num_actions is {self.num_actions} but actions has {actions.num_actions}."
            )
        self.actions = actions
        self.rng = torch.Generator(device=self.device)
        self.rng.manual_seed(check_seed(seed))

    @classmethod
    def for_env(cls, env: EnvBase, seed: int = 0) -> UniformRandomPolicy:
        """Uniform random actions in ``env``'s own action layout, on its device."""
        actions = DiscreteActions.of(env)
        return cls(actions.num_actions, seed=seed, device=env_device(env), actions=actions)

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self.actions.sample(tensordict.batch_size, self.rng, self.device)
        tensordict.set(self.actions.key, action)
        return tensordict


def play_env(env: EnvBase, trajectory_length: int | None = None) -> EnvBase:
    """``env`` set up for play: episodes of at most ``trajectory_length`` steps.

    An env that declares ``play_copy(trajectory_length)`` makes its own (the project's
    envs: a copy that does not stop at the goal; rearrangement resets after every step,
    the key rooms walk 1000 or 1500 random steps, as in the paper). Any other TorchRL
    env is wrapped in torchrl's ``StepCounter(max_steps=trajectory_length)`` (it is not
    copied: collecting steps it); its own episode ends end trajectories too. Its
    ``trajectory_length`` is needed then, as is a batch of parallel envs
    (``batch_size`` ``(N,)``), one image observation ``pixels`` ``[C, H, W]``
    (rename another key with a ``RenameTransform``) and a discrete action
    (``Categorical`` or ``OneHot``).

    Returns:
        the env to collect from; its ``play_trajectory_length`` attribute holds the length.

    Examples:
        >>> from dorp_rl.data import play_env
        >>> from dorp_rl.envs import KeyWallEnv
        >>> env = play_env(KeyWallEnv(batch_size=(2,)), trajectory_length=1000)
        >>> env.max_steps, env.terminate_on_success, env.play_trajectory_length
        (1000, False, 1000)
    """
    if not isinstance(env, EnvBase):
        raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
    length = check_int("trajectory_length", trajectory_length, low=1, optional=True)
    make_copy = getattr(env, "play_copy", None)
    if callable(make_copy):
        out = make_copy(length)
        out.play_trajectory_length = int(out.max_steps)
        return out
    frame_shape_of(env, "pixels")
    actions = DiscreteActions.of(env)
    if actions.key != "action":
        raise ValueError(
            f"{type(env).__name__}'s action key is {actions.key!r}; play data keep 'action' "
            "(rename it with a torchrl RenameTransform)."
        )
    if len(env.batch_size) != 1:
        raise ValueError(
            f"{type(env).__name__} must have one batch dimension (parallel envs, e.g. a "
            f"torchrl ParallelEnv or a batched env) to collect play data, got batch_size "
            f"{list(env.batch_size)}."
        )
    if length is None:
        raise ValueError(
            f"trajectory_length is needed for {type(env).__name__}: how many random steps "
            "one play trajectory lasts (1 gives a fresh reset per transition)."
        )
    out = TransformedEnv(env, StepCounter(max_steps=length))
    out.play_trajectory_length = length
    return out


#: parallel resets :func:`choose_play_length` draws to judge an env's starts
RESET_PROBES = 16
#: steps of a play walk from starts that are (nearly) always the same
PLAY_WALK_LENGTH = 100


def choose_play_length(env: EnvBase, walk_length: int = PLAY_WALK_LENGTH) -> tuple[int, str]:
    """How long each play trajectory of ``env`` lasts when nothing says: 1 (every
    transition from a fresh reset) when its resets start in varied frames, else
    ``walk_length`` random steps from its starts, so that play reaches beyond the first
    step. ``env`` is reset once, whole batch at once (:data:`RESET_PROBES` rows is
    enough); starts are varied when at least half of them differ.

    Returns:
        ``(length, why)``, the length and the reason, for the run's log.

    Examples:
        >>> from dorp_rl.envs import KeyWallEnv
        >>> choose_play_length(KeyWallEnv(batch_size=(16,), seed=0))[0]
        1
    """
    walk_length = check_int("walk_length", walk_length, low=1)
    frames = env.reset().get("pixels", None)
    if frames is None:
        raise ValueError(
            f"{type(env).__name__}'s reset gives no 'pixels'; play data need an image "
            "observation 'pixels' (rename another key with a torchrl RenameTransform)."
        )
    rows = frames.reshape(-1, *frames.shape[-3:]).flatten(1)
    starts = rows.shape[0]
    distinct = int(torch.unique(rows, dim=0).shape[0])
    if 2 * distinct >= starts:
        return 1, f"{distinct} of {starts} resets start in different frames: each from a reset"
    return walk_length, (
        f"only {distinct} distinct frame(s) in {starts} resets: random walks of "
        f"{walk_length} steps from them"
    )


def play_keys(env: EnvBase) -> tuple:
    """The :data:`PLAY_KEYS` that ``env`` has: ``state`` only when it observes one."""
    observed = set(env.full_observation_spec.keys(True, True))
    return tuple(
        k for k in PLAY_KEYS if not (k in ("state", ("next", "state")) and "state" not in observed)
    )


def _steps_per_batch(num_frames: int, num_envs: int, trajectory_length: int) -> int:
    """Steps of each env per collector batch: whole trajectories, or all the frames asked."""
    per_env = math.ceil(num_frames / num_envs)
    return max(1, min(trajectory_length if trajectory_length > 1 else 64, per_env))


def play_segment_length(num_frames: int, num_envs: int, trajectory_length: int) -> int:
    """Longest run of consecutive steps of one trajectory that :func:`collect_play_data` stores.

    The ``num_envs`` envs run side by side and each collector batch is stored env by
    env, so a trajectory is stored whole only when every env steps through it in one
    batch: with few frames (``num_frames < num_envs * trajectory_length``) each env
    stores ``ceil(num_frames / num_envs)`` consecutive steps. Windows and pairs
    (:class:`~dorp_rl.data.SequenceSampler`, :class:`~dorp_rl.data.FuturePairSampler`)
    never span more than this.

    Examples:
        >>> from dorp_rl.data import play_segment_length
        >>> play_segment_length(100_000, 64, 16), play_segment_length(32, 16, 4)
        (16, 2)
    """
    num_frames = check_int("num_frames", num_frames, low=1)
    num_envs = check_int("num_envs", num_envs, low=1)
    trajectory_length = check_int("trajectory_length", trajectory_length, low=1)
    if trajectory_length == 1:
        return 1
    return _steps_per_batch(num_frames, num_envs, trajectory_length)


def check_sampler_fits(
    sampler: Any,
    num_frames: int,
    num_envs: int,
    trajectory_length: int,
    what: str = "the play data",
) -> None:
    """Refuses a sampler whose windows or pairs are longer than any stored trajectory.

    ``sampler.window_length`` (the transitions of one trajectory a sample spans:
    ``max_offset`` of a :class:`~dorp_rl.data.FuturePairSampler`, ``horizon`` of a
    :class:`~dorp_rl.data.SequenceSampler`) must be at most :func:`play_segment_length`;
    samplers without it are not checked.

    Raises:
        ValueError: naming the sampler's length, the trajectories and what to change.
    """
    needed = getattr(sampler, "window_length", None)
    if not isinstance(needed, int):
        return
    longest = play_segment_length(num_frames, num_envs, trajectory_length)
    if needed > longest:
        per_env = math.ceil(num_frames / num_envs)
        cause = (
            f"its trajectories are {trajectory_length} step(s) long"
            if longest == trajectory_length
            else f"num_frames={num_frames} over {num_envs} envs side by side stores "
            f"{per_env} consecutive steps of each trajectory (of {trajectory_length})"
        )
        raise ValueError(
            f"sampler {type(sampler).__name__} spans {needed} consecutive transitions of one "
            f"trajectory, but in {what} {cause}: no sample fits. Use a shorter window or "
            "offset, longer trajectories (trajectory_length) or more num_frames."
        )


def _metadata(env: EnvBase, num_frames: int, seed: int, trajectory_length: int) -> dict:
    return {
        "format_version": _FORMAT_VERSION,
        "env_config": env_identity(env),
        "num_frames": int(num_frames),
        "seed": int(seed),
        "trajectory_length": int(trajectory_length),
        "num_envs": int(env.batch_size.numel()),
        "device": str(env_device(env)),
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
        storage = LazyMemmapStorage(num_frames, scratch_dir=directory / _STORAGE)
    return _buffer(storage, sampler, batch_size)


def _buffer(
    storage: Any, sampler: Sampler | None, batch_size: int | None
) -> TensorDictReplayBuffer:
    kwargs: dict[str, Any] = {"storage": storage, "batch_size": batch_size}
    if sampler is not None:
        kwargs["sampler"] = sampler
    return TensorDictReplayBuffer(**kwargs)


def _metadata_digest(metadata: dict) -> str:
    """SHA-256 of the metadata's own content (all entries but the digest)."""
    body = {k: v for k, v in metadata.items() if k != "metadata_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _key_name(key: str | tuple[str, ...]) -> str:
    return "/".join(key) if isinstance(key, tuple) else key


def _tensor_entries(data: TensorDictBase, directory: Path) -> dict[str, dict[str, Any]]:
    """``{"next/pixels": {"dtype", "shape", "file"}}`` of a memory-mapped storage."""
    entries = {}
    for key, tensor in data.items(include_nested=True, leaves_only=True):
        entries[_key_name(key)] = {
            "dtype": str(tensor.dtype).removeprefix("torch."),
            "shape": list(tensor.shape),
            "file": Path(tensor.filename).resolve().relative_to(directory.resolve()).as_posix(),
        }
    return entries


def _legacy_entries(directory: Path, what: str) -> dict[str, dict[str, Any]]:
    """Tensor entries of a format-1 collection, read from tensordict's ``meta.json`` files."""
    entries: dict[str, dict[str, Any]] = {}

    def walk(folder: Path, prefix: tuple[str, ...]) -> None:
        meta_file = folder / "meta.json"
        try:
            meta = json.loads(meta_file.read_text())
        except (OSError, ValueError) as err:
            raise IntegrityError(f"{what} is damaged: {meta_file} cannot be read ({err}).") from err
        for name, value in meta.items():
            if not isinstance(value, dict):
                continue
            if value.get("type") == "TensorDict":
                walk(folder / name, (*prefix, name))
            elif "shape" in value and "dtype" in value:
                entries[_key_name((*prefix, name))] = {
                    "dtype": str(value["dtype"]).removeprefix("torch."),
                    "shape": list(value["shape"]),
                    "file": (folder / f"{name}.memmap").relative_to(directory).as_posix(),
                }

    walk(directory / _STORAGE, ())
    return entries


def _dtype(name: str, what: str) -> torch.dtype:
    dtype = getattr(torch, str(name), None)
    if not isinstance(dtype, torch.dtype):
        raise IntegrityError(f"{what} is damaged: unknown dtype {name!r} in its metadata.")
    return dtype


def _read_metadata(directory: Path) -> dict[str, Any]:
    meta_path = directory / _METADATA_FILE
    if not meta_path.exists():
        raise FileNotFoundError(f"no play data at {directory}: {_METADATA_FILE} is missing.")
    try:
        metadata = json.loads(meta_path.read_text())
    except (ValueError, UnicodeDecodeError) as err:
        raise IntegrityError(f"play data metadata {meta_path} is corrupted: {err}.") from err
    required = ["format_version", "env_config", "num_frames", "seed", "trajectory_length"]
    if not isinstance(metadata, dict) or any(k not in metadata for k in required):
        raise IntegrityError(
            f"play data metadata {meta_path} is corrupted: expected a JSON object with {required}."
        )
    version = metadata["format_version"]
    if version not in (1, _FORMAT_VERSION):
        raise ValueError(
            f"play data at {directory} has format_version {version!r}, expected "
            f"{_FORMAT_VERSION} (or 1)."
        )
    if version == _FORMAT_VERSION:
        required += ["num_envs", "device", "tensors", "files", "metadata_sha256"]
        missing = [k for k in required if k not in metadata]
        if missing:
            raise IntegrityError(f"play data metadata {meta_path} is corrupted: no {missing}.")
    return metadata


def _check_tensor_files(directory: Path, tensors: dict[str, dict], what: str) -> None:
    """Every tensor's file exists and holds exactly ``numel * itemsize`` bytes (reads nothing)."""
    for key, entry in tensors.items():
        path = directory / entry["file"]
        dtype = _dtype(entry["dtype"], what)
        expected = math.prod(entry["shape"]) * dtype.itemsize
        if not path.is_file():
            raise IntegrityError(f"{what} is incomplete: {path} (key {key!r}) is missing.")
        if path.stat().st_size != expected:
            raise IntegrityError(
                f"{what} is damaged: {path} (key {key!r}) holds {path.stat().st_size} bytes, "
                f"its {entry['shape']} {entry['dtype']} tensor needs {expected}."
            )


def _map_tensors(
    directory: Path, tensors: dict[str, dict], num_frames: int, what: str
) -> TensorDict:
    """The stored tensors, mapped copy-on-write: nothing written to them reaches the files."""
    data = TensorDict(batch_size=[num_frames])
    for key, entry in tensors.items():
        shape = torch.Size(entry["shape"])
        tensor = torch.from_file(
            str(directory / entry["file"]),
            shared=False,
            size=shape.numel(),
            dtype=_dtype(entry["dtype"], what),
        )
        data.set(tuple(key.split("/")), tensor.view(shape))
    return data


def load_play_data(
    directory: str | Path,
    *,
    sampler: Sampler | None = None,
    batch_size: int | None = None,
    expected: dict | None = None,
) -> TensorDictReplayBuffer:
    """Loads play data written by :func:`collect_play_data` (memory-mapped, no copy).

    Before any tensor is mapped, the files are checked against the sizes and SHA-256
    checksums written when the collection completed; the files are then mapped
    copy-on-write, so loading never writes to the data and changes to the returned
    buffer stay in memory. Data of format 1 (written before checksums) are checked for
    their keys and file sizes only, with a warning.

    Args:
        directory: folder given to :func:`collect_play_data`.
        sampler: sampler of the returned buffer (e.g. :class:`FuturePairSampler`).
        batch_size: default sample size of the returned buffer.
        expected: metadata the data must match (entries of :data:`MATCH_FIELDS`); a
            mismatch raises ``ValueError`` naming the differing entries.

    Raises:
        FileNotFoundError: no complete collection in ``directory``.
        IntegrityError: a missing, truncated or changed file, missing keys, or damaged
            metadata (a ``ValueError``; the message names the file).
        ValueError: another format, or data that do not match ``expected``.
    """
    directory = Path(directory)
    what = f"play data at {directory}"
    metadata = _read_metadata(directory)
    legacy = metadata["format_version"] == 1
    if legacy:
        warnings.warn(
            f"{what} has format_version 1, written without checksums: only its keys and file "
            "sizes can be checked. Collect it again into an empty directory to protect it.",
            UserWarning,
            stacklevel=2,
        )
        tensors = _legacy_entries(directory, what)
        metadata.setdefault("device", "cpu")  # format 1 was only ever collected on CPU
    else:
        tensors = metadata["tensors"]
        if not isinstance(tensors, dict) or not tensors:
            raise IntegrityError(f"{what} is damaged: its metadata lists no tensors.")
    num_frames = metadata["num_frames"]
    for key, entry in tensors.items():
        if list(entry["shape"][:1]) != [num_frames]:
            raise IntegrityError(
                f"{what} holds {entry['shape'][0]} frames of {key!r}, its metadata says "
                f"{num_frames}: the collection was probably interrupted, or the metadata edited."
            )
    if not legacy and _metadata_digest(metadata) != metadata["metadata_sha256"]:
        raise IntegrityError(
            f"{what} is damaged: {directory / _METADATA_FILE} changed after it was written "
            "(its checksum does not match its content)."
        )
    if expected is not None:
        diff = config_differences({k: metadata.get(k) for k in expected}, expected)
        if diff:
            lines = format_differences(diff, "stored", "requested")
            raise ValueError(
                f"{what} does not match the request ({lines}); collect into another directory."
            )
    # An env with no state entry stores none (play_keys); a state without its next is cut.
    states = [_key_name(k) for k in ("state", ("next", "state"))]
    needed = [_key_name(k) for k in PLAY_KEYS if _key_name(k) not in states]
    if any(k in tensors for k in states):
        needed += states
    missing = [k for k in needed if k not in tensors]
    if missing:
        raise IntegrityError(
            f"{what} is incomplete: it holds no {missing} (files under "
            f"{directory / _STORAGE} are missing)."
        )
    if not legacy:
        check_sampler_fits(
            sampler, num_frames, metadata["num_envs"], metadata["trajectory_length"], what
        )
        verify_manifest(directory, metadata["files"], what)
    _check_tensor_files(directory, tensors, what)
    data = _map_tensors(directory, tensors, num_frames, what)
    buffer = _buffer(TensorStorage(data), sampler, batch_size)
    buffer.metadata = metadata
    return buffer


def _seal(directory: Path, buffer: TensorDictReplayBuffer, metadata: dict) -> None:
    """Writes ``play_data.json``: tensors, file sizes and checksums (flushed), then its own."""
    metadata = dict(metadata)
    metadata["tensors"] = _tensor_entries(buffer.storage._storage, directory)
    metadata["files"] = file_manifest(directory, _STORAGE)
    metadata["metadata_sha256"] = _metadata_digest(metadata)
    atomic_write_bytes(directory / _METADATA_FILE, json.dumps(metadata, indent=2).encode())


def _claim(directory: Path, wait: bool | float) -> DirectoryLock:
    """Locks ``directory`` for a collection and removes what an interrupted one of ours left.

    Refuses a ``storage/`` folder this library did not write (no lock file next to it):
    nothing is deleted that the library did not write.
    """
    lock = DirectoryLock(directory, _LOCK_FILE, purpose="play data collection")
    storage = directory / _STORAGE
    if storage.exists() and not lock.path.exists():
        raise ValueError(
            f"{directory} already holds a {_STORAGE!r} folder that collect_play_data did not "
            f"write (there is no {_LOCK_FILE} next to it): it is left untouched. Collect into "
            "another directory, or move that folder away."
        )
    lock.acquire(wait)
    if not (directory / _METADATA_FILE).exists():
        shutil.rmtree(storage, ignore_errors=True)  # an interrupted collection of ours
    return lock


def collect_play_data(
    env: EnvBase,
    num_frames: int,
    *,
    directory: str | Path | None = None,
    seed: int = 0,
    trajectory_length: int | None = None,
    sampler: Sampler | None = None,
    batch_size: int | None = None,
    progress: bool = False,
    wait: bool | float = False,
) -> TensorDictReplayBuffer:
    """Collects ``num_frames`` transitions of random play into a replay buffer.

    Runs the paper's exploration with torchrl's :class:`~torchrl.collectors.Collector`:
    uniform random actions drawn from the action spec (:class:`UniformRandomPolicy`) in
    ``play_env(env, trajectory_length)``, whose episodes last ``trajectory_length`` steps
    (by default one step for rearrangement, i.e. a fresh random configuration per
    transition, and 1000 / 1500-step random walks for key-wall / key-corridor; any other
    env needs it given). ``env.batch_size`` envs run side by side.

    Each stored transition holds ``pixels``, ``action``, ``step_count`` (the step within
    its trajectory), ``traj_id``, ``("next", "pixels")`` and, when the env observes one,
    ``state`` and ``("next", "state")``.

    Args:
        env: any TorchRL env with one batch dimension (its parallel envs), an image
            observation ``pixels`` ``[C, H, W]`` (uint8, or floats in ``[0, 1]``) and a
            discrete action (see :func:`play_env`); the project's envs must be
            batch-locked.
        num_frames: transitions to keep.
        directory: if given, data are written there (see the module docstring) and
            checked when loaded. When the folder already holds a complete collection
            made with the same :data:`MATCH_FIELDS` (env, size, seed, trajectory length,
            number of parallel envs, device), it is loaded instead of collected again;
            another collection raises ``ValueError`` naming the differing fields.
        seed: seeds both the env and the exploration policy: same seed, same data.
        trajectory_length: overrides the env's play trajectory length.
        sampler: sampler of the returned buffer (default: uniform over transitions);
            one whose windows or pairs no stored trajectory holds is refused before
            collecting (:func:`check_sampler_fits`).
        batch_size: default sample size of the returned buffer.
        progress: show a tqdm bar.
        wait: when another process is collecting into ``directory``: ``False`` raises
            :class:`~dorp_rl.integrity.DirectoryLockedError` at once, ``True`` waits for
            it (and then loads its data if they match), a number waits that many seconds.

    Raises:
        ValueError: bad arguments, a stored collection that does not match, or a
            ``storage`` folder in ``directory`` that this library did not write.
        DirectoryLockedError: another process is collecting into ``directory``.
        IntegrityError: the stored data are damaged (see :func:`load_play_data`).

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.data import collect_play_data
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(16,))
        >>> buffer = collect_play_data(env, 256, seed=0)
        >>> len(buffer), buffer[0]["pixels"].shape
        (256, torch.Size([3, 16, 16]))
    """
    num_frames = check_int("num_frames", num_frames, low=1)
    seed = check_seed(seed)
    batch_size = check_int("batch_size", batch_size, low=1, optional=True)
    collect_env = play_env(env, trajectory_length)
    metadata = _metadata(env, num_frames, seed, collect_env.play_trajectory_length)
    check_sampler_fits(
        sampler, num_frames, metadata["num_envs"], metadata["trajectory_length"], "this collection"
    )
    if directory is None:
        buffer = _collect(collect_env, num_frames, seed, None, sampler, batch_size, progress)
        buffer.metadata = metadata
        return buffer
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ValueError(f"directory must be a folder, got the file {directory}.")
    request = {k: metadata[k] for k in MATCH_FIELDS}
    if (directory / _METADATA_FILE).exists():
        return load_play_data(directory, sampler=sampler, batch_size=batch_size, expected=request)
    lock = _claim(directory, wait)
    try:
        if not (directory / _METADATA_FILE).exists():  # else: done by the process we waited for
            buffer = _collect(collect_env, num_frames, seed, directory, sampler, None, progress)
            _seal(directory, buffer, metadata)
            del buffer
    finally:
        lock.release()
    return load_play_data(directory, sampler=sampler, batch_size=batch_size, expected=request)


def _collect(
    collect_env: EnvBase,
    num_frames: int,
    seed: int,
    directory: Path | None,
    sampler: Sampler | None,
    batch_size: int | None,
    progress: bool,
) -> TensorDictReplayBuffer:
    """Runs the collector into a fresh buffer (in memory, or memory-mapped in ``directory``)."""
    length = collect_env.play_trajectory_length
    num_envs = int(collect_env.batch_size.numel())
    # Whole trajectories per collector batch keep each walk contiguous in storage.
    steps_per_batch = _steps_per_batch(num_frames, num_envs, length)
    frames_per_batch = num_envs * steps_per_batch
    total_frames = math.ceil(num_frames / frames_per_batch) * frames_per_batch

    collect_env.set_seed(seed)
    policy = UniformRandomPolicy.for_env(collect_env, seed=derive_seed(seed, 1))
    keys = play_keys(collect_env)
    collector = Collector(
        collect_env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        device=env_device(collect_env),
        trust_policy=True,
    )
    buffer = _make_buffer(num_frames, directory, sampler, batch_size, env_device(collect_env))
    bar = progress_bar(progress, total=num_frames, desc="play data", unit="frame")
    stored = 0
    try:
        for batch in collector:
            batch = batch.reshape(-1)  # env-major: each env's steps stay consecutive
            batch.set("traj_id", batch.get(("collector", "traj_ids")))
            take = min(num_frames - stored, batch.shape[0])
            buffer.extend(batch[:take].select(*keys).cpu())
            stored += take
            if bar is not None:
                bar.update(take)
            if stored >= num_frames:
                break
    finally:
        collector.shutdown()
        if bar is not None:
            bar.close()
    return buffer


def check_play_buffer(
    buffer: Any,
    env: EnvBase,
    *,
    min_trajectory_length: int = 1,
    name: str = "buffer",
) -> None:
    """Checks that a replay buffer holds play data of ``env`` that a trainer can use.

    A buffer from :func:`collect_play_data` / :func:`load_play_data` carries its
    ``metadata``: its environment must be ``env``'s and its trajectories at least
    ``min_trajectory_length`` steps long. Any other buffer must hold ``env``'s
    :func:`play_keys` with its state shape.

    Raises:
        ValueError: naming ``name`` and what does not fit.
    """
    if not isinstance(buffer, TensorDictReplayBuffer):
        raise ValueError(
            f"{name} must be a TensorDictReplayBuffer of play data (collect_play_data), "
            f"got {type(buffer).__name__}."
        )
    if len(buffer) == 0:
        raise ValueError(f"{name} is empty.")
    metadata = getattr(buffer, "metadata", None)
    if isinstance(metadata, dict) and "env_config" in metadata:
        diff = config_differences(metadata["env_config"], env_identity(env))
        if diff:
            details = format_differences(diff, name, "config")
            raise ValueError(f"{name} holds play data of another environment ({details}).")
        length = metadata.get("trajectory_length", min_trajectory_length)
        if length < min_trajectory_length:
            raise ValueError(
                f"{name} holds trajectories of {length} step(s), this config needs at least "
                f"{min_trajectory_length}."
            )
        return
    first = buffer[:1]
    keys = set(first.keys(True, True))
    missing = [k for k in play_keys(env) if k not in keys]
    if missing:
        raise ValueError(f"{name} lacks the play-data keys {missing} (see collect_play_data).")
    if "state" not in play_keys(env):
        return
    state = first.get("state")
    state_shape = list(env.full_observation_spec["state"].shape[len(env.batch_size) :])
    if list(state.shape[1:]) != state_shape:
        raise ValueError(
            f"{name} holds states of shape {list(state.shape[1:])}, {type(env).__name__} has "
            f"{state_shape}: the data come from another environment."
        )
