"""The one checkpoint format of dorp-rl: config, state dicts, step, RNG states, versions.

Checkpoints are written to a temporary file and renamed, so an interrupted write never
leaves a half file under the real name. Loading checks the kind of checkpoint and the
environment it was trained on, and says what does not fit.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_FORMAT = 1


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
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(
    path: str | Path,
    *,
    kind: str | None = None,
    env_config: dict[str, Any] | None = None,
    map_location: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Reads a checkpoint written by :func:`save_checkpoint` and checks that it fits.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a readable dorp-rl checkpoint (corrupted or foreign),
            is of another ``kind``, or comes from another environment (the message lists
            the differing entries).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}.")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:
        raise ValueError(f"checkpoint {path} is corrupted or not a torch file ({err}).") from err
    if not isinstance(payload, dict) or "format" not in payload:
        raise ValueError(f"{path} is not a dorp-rl checkpoint (no 'format' entry).")
    if payload["format"] != CHECKPOINT_FORMAT:
        raise ValueError(
            f"checkpoint {path} has format {payload['format']}, this version reads "
            f"format {CHECKPOINT_FORMAT}."
        )
    if kind is not None and payload.get("kind") != kind:
        raise ValueError(
            f"checkpoint {path} holds a {payload.get('kind')!r} model, expected {kind!r}."
        )
    if env_config is not None:
        stored = payload.get("env_config", {})
        keys = sorted(set(stored) | set(env_config))
        diff = [k for k in keys if stored.get(k) != env_config.get(k)]
        if diff:
            details = "; ".join(
                f"{k}: checkpoint {stored.get(k)!r}, requested {env_config.get(k)!r}" for k in diff
            )
            raise ValueError(f"checkpoint {path} was trained on another environment ({details}).")
    return payload
