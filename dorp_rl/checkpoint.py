"""The one checkpoint format of dorp-rl: config, state dicts, step, RNG states, versions.

A checkpoint file is a torch file holding ``{"format", "kind", "sha256", "payload"}``:
``payload`` is the serialised checkpoint (a uint8 tensor of its bytes) and ``sha256``
its checksum, so a changed byte
anywhere in the payload is refused instead of loaded. Files are written to a temporary
name, flushed and renamed, so an interrupted write never leaves a half file under the
real name; weights with NaN or infinite values are neither written nor loaded. Loading
checks the kind of checkpoint, its entries and the environment it was trained on, and
says what does not fit.
"""

from __future__ import annotations

import hashlib
import io
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from dorp_rl.config import config_differences, format_differences
from dorp_rl.integrity import IntegrityError, atomic_write_bytes, non_finite_entries

#: 2: checksummed payload. 1 (read with a warning): the payload itself, no checksum.
CHECKPOINT_FORMAT = 2
#: Entries every checkpoint payload has.
REQUIRED_ENTRIES = ("format", "kind", "config", "env_config", "state", "step")


def library_versions() -> dict[str, str]:
    """Versions of the libraries a checkpoint depends on."""
    import tensordict
    import torchrl

    import dorp_rl

    return {
        "dorp_rl": dorp_rl.__version__,
        "torch": str(torch.__version__),
        "torchrl": str(torchrl.__version__),
        "tensordict": str(tensordict.__version__),
    }


def _non_finite_message(path: Path, entries: list[str], verb: str) -> str:
    shown = ", ".join(entries[:5]) + (f" and {len(entries) - 5} more" if len(entries) > 5 else "")
    return (
        f"{verb} checkpoint {path}: NaN or infinite values in {shown}. The run it "
        "comes from diverged; use an earlier checkpoint."
    )


def save_checkpoint(
    path: str | Path,
    *,
    kind: str,
    config: dict[str, Any],
    env_config: dict[str, Any],
    state: dict[str, Any],
    step: int,
    rng: dict[str, torch.Tensor] | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Writes a checkpoint atomically and returns its path.

    Args:
        path: destination file.
        kind: what was trained (e.g. ``"representation"``, ``"world_model"``).
        config: the training config as a plain dict.
        env_config: ``env.config()`` of the environment the data came from.
        state: state dicts (model, optimiser, ...).
        step: gradient steps done.
        rng: generator states needed to continue identically.
        extra: anything else JSON-like (metrics, restart counters).

    Raises:
        IntegrityError: ``state`` holds NaN or infinite values (the file is not written,
            so an earlier checkpoint under ``path`` stays as it was).
    """
    path = Path(path)
    bad = non_finite_entries(state)
    if bad:
        raise IntegrityError(_non_finite_message(path, bad, "refusing to write"))
    payload = {
        "format": CHECKPOINT_FORMAT,
        "kind": kind,
        "config": config,
        "env_config": env_config,
        "state": state,
        "step": int(step),
        "rng": rng or {},
        "extra": extra or {},
        "versions": library_versions(),
    }
    inner = io.BytesIO()
    torch.save(payload, inner)
    data = inner.getvalue()
    outer = io.BytesIO()
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "kind": kind,
            "sha256": hashlib.sha256(data).hexdigest(),
            # raw bytes as a uint8 tensor: stored as is (pickled bytes would be re-encoded)
            "payload": torch.frombuffer(bytearray(data), dtype=torch.uint8),
        },
        outer,
    )
    return atomic_write_bytes(path, outer.getvalue())


def _read_payload(path: Path, map_location: str | torch.device) -> dict[str, Any]:
    try:
        outer = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:
        raise IntegrityError(
            f"checkpoint {path} is corrupted or not a torch file ({err})."
        ) from err
    if not isinstance(outer, dict) or "format" not in outer:
        raise IntegrityError(f"{path} is not a dorp-rl checkpoint (no 'format' entry).")
    if outer["format"] == 1:  # written before checksums
        warnings.warn(
            f"checkpoint {path} has format 1, written without a checksum: a damaged file "
            "cannot be told from a good one. Save it again to protect it.",
            UserWarning,
            stacklevel=3,
        )
        return outer
    if outer["format"] != CHECKPOINT_FORMAT:
        raise IntegrityError(
            f"checkpoint {path} has format {outer['format']!r}, this version reads formats 1 "
            f"and {CHECKPOINT_FORMAT}."
        )
    data, expected = outer.get("payload"), outer.get("sha256")
    if (
        not isinstance(data, torch.Tensor)
        or data.dtype != torch.uint8
        or not isinstance(expected, str)
    ):
        raise IntegrityError(f"checkpoint {path} is corrupted: no payload or checksum.")
    data = data.cpu().numpy().tobytes()
    if hashlib.sha256(data).hexdigest() != expected:
        raise IntegrityError(
            f"checkpoint {path} is corrupted: its content does not match its SHA-256 "
            "checksum (the file changed after it was written)."
        )
    try:
        payload = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except Exception as err:  # a checksummed payload that does not load: another version
        raise IntegrityError(f"checkpoint {path} could not be read ({err}).") from err
    if not isinstance(payload, dict):
        raise IntegrityError(f"checkpoint {path} is corrupted: its payload is not a dict.")
    return payload


def load_checkpoint(
    path: str | Path,
    *,
    kind: str | None = None,
    env_config: dict[str, Any] | None = None,
    map_location: str | torch.device = "cpu",
    state_keys: Sequence[str] = (),
) -> dict[str, Any]:
    """Reads a checkpoint written by :func:`save_checkpoint` and checks that it fits.

    Args:
        path: the checkpoint file.
        kind: the kind it must hold (``None``: any).
        env_config: the environment it must come from (``None``: any).
        map_location: where tensors are loaded.
        state_keys: entries its ``state`` must have (e.g. ``("encoder",)``).

    Raises:
        FileNotFoundError: no file at ``path``.
        IntegrityError: the file is damaged (checksum mismatch, unreadable), lacks an
            entry, or holds NaN or infinite values (a ``ValueError``).
        ValueError: the file is of another ``kind`` or comes from another environment
            (the message lists the differing entries).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}.")
    payload = _read_payload(path, map_location)
    missing = [k for k in REQUIRED_ENTRIES if k not in payload]
    if missing:
        raise IntegrityError(
            f"checkpoint {path} is incomplete: it has no {', '.join(map(repr, missing))} "
            f"entry (it holds {sorted(payload)})."
        )
    if kind is not None and payload["kind"] != kind:
        raise ValueError(f"checkpoint {path} holds a {payload['kind']!r} model, expected {kind!r}.")
    state = payload["state"]
    if not isinstance(state, dict):
        raise IntegrityError(f"checkpoint {path} is corrupted: its 'state' is not a dict.")
    missing = [k for k in state_keys if k not in state]
    if missing:
        raise IntegrityError(
            f"checkpoint {path} is incomplete: its state has no {', '.join(map(repr, missing))} "
            f"entry (it holds {sorted(state)}); was it written by another trainer?"
        )
    if env_config is not None:
        diff = config_differences(payload.get("env_config") or {}, env_config)
        if diff:
            details = format_differences(diff, "checkpoint", "requested")
            raise ValueError(f"checkpoint {path} was trained on another environment ({details}).")
    bad = non_finite_entries(state)
    if bad:
        raise IntegrityError(_non_finite_message(path, bad, "refusing to load"))
    return payload


def load_module_state(
    module: nn.Module, state: dict[str, Any], path: str | Path, entry: str
) -> None:
    """``module.load_state_dict(state)``; a mismatch raises a ``ValueError`` naming the file and entry."""
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError, TypeError) as err:
        raise ValueError(
            f"checkpoint {path}: its {entry!r} weights do not fit this {type(module).__name__} "
            f"({err})."
        ) from err
