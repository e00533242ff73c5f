"""What keeps files on disk whole: checksums, atomic writes, directory locks, finite weights.

- :func:`sha256_file` and :func:`file_manifest` / :func:`verify_manifest`: the sizes and
  SHA-256 checksums of a set of files, written when a data set is complete and checked
  before it is read (:mod:`dorp_rl.data`).
- :func:`atomic_write_bytes`: a file is written under a temporary name, flushed to disk
  and renamed, so an interrupted write never leaves half a file under the real name
  (checkpoints, metadata).
- :class:`DirectoryLock`: an OS lock on a file in a directory, so that two processes
  never write into one directory at once; the OS drops it when its process dies.
- :func:`non_finite_entries`: the NaN / infinite tensors of a nested state dict.
- :func:`state_digest`: a SHA-256 of a module's weights, so that what was built on one
  module (a latent world model learning an encoder's codes) can tell it from another.

Errors: :class:`IntegrityError` (a damaged, incomplete or non-finite file) and
:class:`DirectoryLockedError`, both ``ValueError`` subclasses.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "DirectoryLock",
    "DirectoryLockedError",
    "IntegrityError",
    "atomic_write_bytes",
    "file_manifest",
    "non_finite_entries",
    "sha256_file",
    "state_digest",
    "verify_manifest",
]

_CHUNK = 1 << 22


class IntegrityError(ValueError):
    """A file written by dorp-rl is damaged, incomplete or holds non-finite weights."""


class DirectoryLockedError(ValueError):
    """The directory is being written by another process (or another object of this one)."""


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Writes ``data`` to ``path`` through a flushed temporary file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    _fsync_dir(path.parent)
    return path


def _files_under(root: Path) -> Iterator[Path]:
    for path in sorted(root.rglob("*")):
        if path.is_file():
            yield path


def file_manifest(directory: str | Path, subdir: str) -> dict[str, dict[str, Any]]:
    """``{relative path: {"bytes", "sha256"}}`` of every file under ``directory / subdir``.

    Each file is flushed to disk first (``fsync``), so the manifest describes what a
    crash would leave.
    """
    directory = Path(directory)
    manifest = {}
    for path in _files_under(directory / subdir):
        with open(path, "rb+") as handle:
            os.fsync(handle.fileno())
        manifest[path.relative_to(directory).as_posix()] = {
            "bytes": path.stat().st_size,
            "sha256": sha256_file(path),
        }
    return manifest


def verify_manifest(
    directory: str | Path, manifest: Mapping[str, Mapping[str, Any]], what: str
) -> None:
    """Checks that every file of ``manifest`` is there with its size and checksum.

    Sizes are checked for all files before any checksum is computed. Reads only.

    Raises:
        IntegrityError: naming the first missing, resized or changed file.
    """
    directory = Path(directory)
    for name, entry in manifest.items():
        path = directory / name
        if not path.is_file():
            raise IntegrityError(
                f"{what} is incomplete: {path} is missing (it was written when the data "
                "were collected). Collect the data again into an empty directory."
            )
        size = path.stat().st_size
        if size != entry["bytes"]:
            raise IntegrityError(
                f"{what} is damaged: {path} holds {size} bytes, {entry['bytes']} were "
                "written (truncated or overwritten). Collect the data again into an empty "
                "directory."
            )
    for name, entry in manifest.items():
        path = directory / name
        if sha256_file(path) != entry["sha256"]:
            raise IntegrityError(
                f"{what} is damaged: the content of {path} changed since it was written "
                "(SHA-256 mismatch). Collect the data again into an empty directory."
            )


def state_digest(module: torch.nn.Module) -> str:
    """SHA-256 (hex) of ``module``'s state dict: names, dtypes, shapes and values.

    Equal for two modules with the same weights, on any device; any changed value,
    shape or name changes it.

    Examples:
        >>> import torch
        >>> from dorp_rl.integrity import state_digest
        >>> a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
        >>> state_digest(a) == state_digest(a), state_digest(a) == state_digest(b)
        (True, False)
    """
    digest = hashlib.sha256()
    for name, tensor in module.state_dict().items():
        tensor = tensor.detach().to("cpu").contiguous()
        digest.update(f"{name}:{tensor.dtype}:{tuple(tensor.shape)};".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def non_finite_entries(state: Any, prefix: str = "") -> list[str]:
    """Paths (``"encoder.extractor.0.weight"``) of floating tensors with NaN or inf values.

    Walks nested dicts, lists and tuples (state dicts, optimiser states).
    """
    found: list[str] = []
    if isinstance(state, torch.Tensor):
        floating = state.is_floating_point() or state.is_complex()
        if floating and state.numel() and not bool(torch.isfinite(state).all()):
            found.append(prefix or "<tensor>")
    elif isinstance(state, Mapping):
        for key, value in state.items():
            found += non_finite_entries(value, f"{prefix}.{key}" if prefix else str(key))
    elif isinstance(state, (list, tuple)):
        for i, value in enumerate(state):
            found += non_finite_entries(value, f"{prefix}[{i}]")
    return found


class DirectoryLock:
    """An exclusive lock on ``directory / name`` held while a directory is written.

    Uses an OS file lock (``fcntl.flock``), which the OS drops when the process dies, so
    a killed run never leaves a stale lock behind. The lock file stays: it also records
    that the library writes in this directory (who and when, for the error message).

    Args:
        directory: the directory to guard (created if needed).
        name: the lock file's name.
        purpose: what is written there, for the error message.

    Examples:
        >>> import tempfile
        >>> from dorp_rl.integrity import DirectoryLock, DirectoryLockedError
        >>> folder = tempfile.mkdtemp()
        >>> with DirectoryLock(folder, purpose="play data"):
        ...     try:
        ...         DirectoryLock(folder, purpose="play data").acquire()
        ...     except DirectoryLockedError:
        ...         print("busy")
        busy
    """

    def __init__(
        self, directory: str | Path, name: str = ".dorp_rl.lock", purpose: str = ""
    ) -> None:
        self.directory = Path(directory)
        self.path = self.directory / name
        self.purpose = purpose
        self._handle = None

    def _holder(self) -> str:
        try:
            info = json.loads(self.path.read_text())
            return f"process {info.get('pid')} on {info.get('host')} since {info.get('since')}"
        except (OSError, ValueError):
            return "another process"

    def acquire(self, wait: bool | float = False, poll: float = 0.2) -> DirectoryLock:
        """Takes the lock; ``wait``: ``False`` fails at once, ``True`` waits, a number waits that many seconds.

        Raises:
            DirectoryLockedError: the lock is held and the wait is over.
        """
        if self._handle is not None:
            return self
        self.directory.mkdir(parents=True, exist_ok=True)
        handle = open(self.path, "a+")  # noqa: SIM115 - held until release()
        deadline = None if wait is True else time.monotonic() + float(wait or 0.0)
        while True:
            try:
                _lock(handle)
                break
            except BlockingIOError:
                if deadline is not None and time.monotonic() >= deadline:
                    holder = self._holder()
                    handle.close()
                    what = f" ({self.purpose})" if self.purpose else ""
                    raise DirectoryLockedError(
                        f"{self.directory} is being written by {holder}{what}: two writers "
                        f"would mix their files. Wait for it (wait=True), or use another "
                        f"directory. Lock file: {self.path}."
                    ) from None
                time.sleep(poll)
        handle.seek(0)
        handle.truncate()
        since = time.strftime("%Y-%m-%d %H:%M:%S")
        handle.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "since": since}))
        handle.flush()
        self._handle = handle
        return self

    def release(self) -> None:
        """Drops the lock (the lock file stays)."""
        if self._handle is not None:
            _unlock(self._handle)
            self._handle.close()
            self._handle = None

    @property
    def held(self) -> bool:
        return self._handle is not None

    def __enter__(self) -> DirectoryLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        self.release()


def _lock(handle: Any) -> None:
    if fcntl is not None:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    import msvcrt  # pragma: no cover - Windows

    try:  # pragma: no cover
        msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, 1)
    except OSError as err:  # pragma: no cover
        raise BlockingIOError(str(err)) from err


def _unlock(handle: Any) -> None:
    if fcntl is not None:
        fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
        return
    import msvcrt  # pragma: no cover - Windows

    handle.seek(0)  # pragma: no cover
    msvcrt.locking(handle.fileno(), msvcrt.LK_UNLCK, 1)  # pragma: no cover
