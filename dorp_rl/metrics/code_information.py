"""Label-free statistics of discrete codes: how much each one-hot says, and how much of it is its own.

Ground-truth diagnostics (:mod:`dorp_rl.metrics.diagnostics`) need the environment's state.
These need only codes of unlabeled frames, so a trainer can use them to compare runs.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


def _check_codes(codes: torch.Tensor) -> torch.Tensor:
    if not isinstance(codes, torch.Tensor):
        raise ValueError(f"codes must be a torch.Tensor, got {type(codes).__name__}.")
    if codes.dim() != 2 or codes.shape[0] == 0 or codes.shape[1] == 0:
        raise ValueError(f"codes must have shape [N, C] with N, C >= 1, got {list(codes.shape)}.")
    if codes.dtype.is_floating_point or codes.dtype == torch.bool:
        raise ValueError(f"codes must be an integer tensor, got {codes.dtype}.")
    if bool((codes < 0).any()):
        raise ValueError("codes must be >= 0 (code indices).")
    return codes.long().cpu()


def _entropy(counts: torch.Tensor) -> float:
    p = counts[counts > 0].double() / counts.sum()
    return float(-(p * p.log()).sum())


def code_information(codes: torch.Tensor) -> dict[str, object]:
    """Plug-in entropies and pairwise mutual information of C one-hots' codes, in nats.

    ``unique_information`` is ``sum_i [H(z_i) - sum_{j != i} I(z_i; z_j)]``: the
    information the one-hots carry, minus what any two of them share. It is high when
    every one-hot uses many codes and says something the others do not (an
    object-factorized code), and low when a one-hot uses few codes or repeats another
    one (key rooms: an agent one-hot that also codes whether the key is taken).

    Args:
        codes: int ``[N, C]`` codes of N frames (e.g. play data).

    Returns:
        ``entropy`` (list of C floats), ``mutual_information`` (C x C nested list, the
        diagonal holds the entropies) and ``unique_information`` (float).

    Examples:
        >>> import torch
        >>> from dorp_rl.metrics import code_information
        >>> a = torch.arange(1000) % 4
        >>> info = code_information(torch.stack([a, a], -1))  # one one-hot repeated
        >>> round(info["entropy"][0], 3), round(info["unique_information"], 3)
        (1.386, 0.0)
    """
    codes = _check_codes(codes)
    num = codes.shape[1]
    sizes = (codes.max(0).values + 1).tolist()
    entropy = [_entropy(torch.bincount(codes[:, i], minlength=sizes[i])) for i in range(num)]
    mutual = [[0.0] * num for _ in range(num)]
    for i in range(num):
        mutual[i][i] = entropy[i]
        for j in range(i + 1, num):
            joint = torch.bincount(codes[:, i] * sizes[j] + codes[:, j])
            value = max(0.0, entropy[i] + entropy[j] - _entropy(joint))
            mutual[i][j] = mutual[j][i] = value
    shared = sum(mutual[i][j] for i in range(num) for j in range(num) if i != j)
    return {
        "entropy": entropy,
        "mutual_information": mutual,
        "unique_information": sum(entropy) - shared,
    }


def code_dynamics(
    codes: torch.Tensor,
    next_codes: torch.Tensor,
    traj_id: torch.Tensor | None = None,
    step_count: torch.Tensor | None = None,
    *,
    window: int = 3,
) -> dict[str, list]:
    """How each one-hot's code moves along play transitions, with no labels.

    Args:
        codes: int ``[N, C]`` codes of the transitions' frames.
        next_codes: int ``[N, C]`` codes of their next frames.
        traj_id: int ``[N]`` trajectory of each transition; with ``step_count``
            (``[N]``, the step within it) it orders the transitions, so that an undone
            change can be found. ``None``: undo rates are not computed.
        step_count: int ``[N]``, see ``traj_id``.
        window: a change counts as undone when the code is back to what it was within
            this many further steps of the same trajectory.

    Returns:
        per one-hot lists: ``codes_used`` (distinct codes over both frames),
        ``change_rate`` (share of transitions whose code changes), ``undo_rate`` (share
        of changes undone within ``window`` steps; ``None`` when no change has that many
        steps after it in its trajectory), and ``dead``: one-hots whose code never changes
        (two-code one-hots such as a key bit included), which code nothing about play.

    Examples:
        >>> import torch
        >>> from dorp_rl.metrics import code_dynamics
        >>> codes = torch.tensor([[0, 1], [1, 1], [0, 1], [0, 1]])
        >>> next_codes = torch.tensor([[1, 1], [0, 1], [0, 1], [0, 1]])
        >>> out = code_dynamics(codes, next_codes, torch.zeros(4), torch.arange(4), window=2)
        >>> out["change_rate"], out["undo_rate"], out["dead"]
        ([0.5, 0.0], [0.5, None], [False, True])
    """
    codes, next_codes = _check_codes(codes), _check_codes(next_codes)
    if codes.shape != next_codes.shape:
        raise ValueError(
            f"codes and next_codes must have the same shape [N, C], got {list(codes.shape)} "
            f"and {list(next_codes.shape)}."
        )
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be an int >= 1, got {window!r}.")
    n, num = codes.shape
    changed = codes != next_codes  # [N, C]
    both = torch.cat([codes, next_codes])
    used = [int(both[:, i].unique().numel()) for i in range(num)]
    change_rate = changed.double().mean(0).tolist()
    undo: list = [None] * num
    if (traj_id is None) != (step_count is None):
        raise ValueError("traj_id and step_count go together: give both or neither.")
    if traj_id is not None:
        traj = torch.as_tensor(traj_id).reshape(-1).long().cpu()
        step = torch.as_tensor(step_count).reshape(-1).long().cpu()
        if traj.numel() != n or step.numel() != n:
            raise ValueError(
                f"traj_id and step_count must hold one value per transition ({n}), got "
                f"{traj.numel()} and {step.numel()}."
            )
        order = torch.argsort(traj * (int(step.max()) + 1) + step)
        traj, step = traj[order], step[order]
        codes, next_codes, changed = codes[order], next_codes[order], changed[order]
        # A change at i is checkable when steps i+1 .. i+window follow it in one trajectory.
        checkable = torch.zeros(n, dtype=torch.bool)
        undone = torch.zeros(n, num, dtype=torch.bool)
        if n > window:
            span = torch.ones(n - window, dtype=torch.bool)
            for k in range(1, window + 1):
                later = slice(k, n - window + k)
                span &= (traj[later] == traj[: n - window]) & (
                    step[later] == step[: n - window] + k
                )
                undone[: n - window] |= next_codes[later] == codes[: n - window]
            checkable[: n - window] = span
        for i in range(num):
            events = changed[:, i] & checkable
            if bool(events.any()):
                undo[i] = float((undone[:, i] & events).sum() / events.sum())
    return {
        "codes_used": used,
        "change_rate": change_rate,
        "undo_rate": undo,
        "dead": [rate == 0.0 for rate in change_rate],
    }


def play_code_dynamics(
    buffer: Any,
    encoder: nn.Module,
    *,
    window: int = 3,
    chunk_size: int = 1024,
    transitions: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> dict[str, list]:
    """:func:`code_dynamics` of an encoder's codes on a play buffer of any env.

    Encodes both frames of every transition (:func:`~dorp_rl.planners.encode_transitions`,
    or takes its result as ``transitions``) and orders them by the buffer's ``traj_id``
    and ``step_count``.
    """
    from dorp_rl.data.samplers import stored_column
    from dorp_rl.planners.play_codes import encode_transitions

    if transitions is None:
        transitions = encode_transitions(buffer, encoder, chunk_size=chunk_size)
    codes, next_codes = transitions
    storage = getattr(buffer, "storage", None)
    if storage is None:  # a TensorDict of transitions
        columns = [buffer.get(key, None) for key in ("traj_id", "step_count")]
    else:  # the two columns only, not the frames
        present = storage[:1].keys()
        columns = [
            stored_column(storage, k) if k in present else None for k in ("traj_id", "step_count")
        ]
    return code_dynamics(codes, next_codes, *columns, window=window)
