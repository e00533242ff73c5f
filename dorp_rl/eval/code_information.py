"""Label-free statistics of discrete codes: how much each one-hot says, and how much of it is its own.

Ground-truth diagnostics (:mod:`dorp_rl.eval.diagnostics`) need the environment's state.
These need only codes of unlabeled frames, so a trainer can use them to compare runs.
"""

from __future__ import annotations

import torch


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
        >>> from dorp_rl.eval import code_information
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
