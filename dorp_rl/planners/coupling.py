"""Which one-hots a code graph must plan together, read from the play data's codes.

DORP plans each group of one-hots on its own graph. That is right for objects that move
independently (blocks: each block's code can change whatever the others' codes are), and
wrong for one-hots that depend on each other: a key that is taken only where the agent
stands, two one-hots that follow the same object. :func:`coupled_groups` finds those from
the codes of play transitions alone and joins them into one group:

- one-hot ``i`` *depends on* one-hot ``j`` when where ``i``'s code changes is told by
  ``j``'s code: the mutual information between "``i`` changed" and ``j``'s code before the
  step, as a share of the entropy of "``i`` changed", is at least ``dependence`` (blocks
  that only block each other now and then share almost nothing: 0.002 or less; a key
  taken next to the agent, 0.1 to 0.3);
- ``i`` and ``j`` *change together* when at least ``co_change`` of the rarer one's changes
  come in a step that changes the other too (two one-hots of one object).

Groups are the connected components of these relations; a one-hot whose code never
changes is a group of its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dorp_rl.validation import check_float

__all__ = ["GroupChoice", "coupled_groups"]


@dataclass(frozen=True)
class GroupChoice:
    """The groups :func:`coupled_groups` chose and why.

    Attributes:
        groups: one tuple of one-hot indices per group, in order of their first member.
        dependence: float ``[C, C]``: row ``i``, column ``j``, the share of the entropy
            of "one-hot ``i`` changed" that one-hot ``j``'s code tells (0 on the diagonal).
        co_change: float ``[C, C]``: the share of the rarer one-hot's changes that come in
            a step changing the other one too (0 on the diagonal).
        why: one line per joined pair, for the run's log.
    """

    groups: tuple[tuple[int, ...], ...]
    dependence: torch.Tensor
    co_change: torch.Tensor
    why: str


def _entropy_bits(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(0.0, 1.0)
    terms = torch.where(p > 0, -p * torch.log2(p.clamp_min(1e-30)), torch.zeros_like(p))
    return terms + torch.where(
        p < 1, -(1 - p) * torch.log2((1 - p).clamp_min(1e-30)), torch.zeros_like(p)
    )


def coupled_groups(
    codes: torch.Tensor,
    next_codes: torch.Tensor,
    *,
    dependence: float = 0.03,
    co_change: float = 0.5,
) -> GroupChoice:
    """Groups of one-hots to plan together, from the codes of play transitions.

    Args:
        codes: int64 ``[N, C]``, the code of each transition's first frame.
        next_codes: int64 ``[N, C]``, the code of the frame after it.
        dependence: the share of entropy (module docstring) from which one one-hot's
            changes depend on another's code, in ``(0, 1]``.
        co_change: the share of shared changes from which two one-hots change together,
            in ``(0, 1]``.

    Returns:
        a :class:`GroupChoice`.

    Examples:
        >>> import torch
        >>> g = torch.Generator().manual_seed(0)
        >>> agent = torch.randint(0, 8, (4000,), generator=g)  # an agent on 8 places
        >>> block = torch.randint(0, 8, (4000,), generator=g)  # a block that moves anywhere
        >>> key = torch.randint(0, 2, (4000,), generator=g)  # a key, taken or not
        >>> action = torch.randint(0, 3, (4000,), generator=g)  # move agent, block; take
        >>> nxt_agent = torch.where(action == 0, torch.randint(0, 8, (4000,), generator=g), agent)
        >>> nxt_block = torch.where(action == 1, torch.randint(0, 8, (4000,), generator=g), block)
        >>> nxt_key = torch.where((action == 2) & (agent == 3), 1 - key, key)  # only at 3
        >>> codes = torch.stack([agent, key, block], 1)
        >>> choice = coupled_groups(codes, torch.stack([nxt_agent, nxt_key, nxt_block], 1))
        >>> choice.groups
        ((0, 1), (2,))
    """
    dependence = check_float("dependence", dependence, low=0.0, low_open=True, high=1.0)
    co_change = check_float("co_change", co_change, low=0.0, low_open=True, high=1.0)
    if codes.shape != next_codes.shape or codes.dim() != 2 or codes.shape[0] < 1:
        raise ValueError(
            "codes and next_codes must be int64 tensors of one shape [N, C] with N >= 1, got "
            f"{list(codes.shape)} and {list(next_codes.shape)}."
        )
    n, c = codes.shape
    changed = (codes != next_codes).double()  # [N, C]
    p_change = changed.mean(0)  # [C]
    h_change = _entropy_bits(p_change)  # [C]
    shared = torch.zeros(c, c, dtype=torch.float64)
    # the share of the rarer one-hot's changes that come with the other's
    both = changed.T @ changed / n  # [C, C]
    rarer = torch.minimum(p_change[:, None], p_change[None, :])
    together = torch.where(rarer > 0, both / rarer.clamp_min(1e-30), 0.0)
    for j in range(c):
        values, index = torch.unique(codes[:, j], return_inverse=True)
        p_code = torch.bincount(index, minlength=len(values)).double() / n  # [V]
        # P(i changed | j's code = v) for every i and v
        sums = torch.zeros(len(values), c, dtype=torch.float64).index_add_(0, index, changed)
        p_given = sums / (p_code[:, None] * n)
        h_given = (p_code[:, None] * _entropy_bits(p_given)).sum(0)  # [C]
        # less the estimate's bias (Miller-Madow): rare changes would seem told otherwise
        bias = (len(values) - 1) / (2 * n * math.log(2))
        info = (h_change - h_given - bias).clamp_min(0.0)
        shared[:, j] = torch.where(h_change > 0, info / h_change.clamp_min(1e-30), 0.0)
    shared.fill_diagonal_(0.0)
    together.fill_diagonal_(0.0)
    joined = (shared >= dependence) | (together >= co_change)
    joined = joined | joined.T
    group_of = list(range(c))

    def root(i: int) -> int:
        while group_of[i] != i:
            group_of[i] = group_of[group_of[i]]
            i = group_of[i]
        return i

    reasons = []
    for i in range(c):
        for j in range(i + 1, c):
            if not bool(joined[i, j]):
                continue
            group_of[root(j)] = root(i)
            told = max(float(shared[i, j]), float(shared[j, i]))
            reasons.append(
                f"one-hots {i} and {j}: {told:.2f} of where one changes is told by the "
                f"other's code, {float(together[i, j]):.2f} of the rarer's changes shared"
            )
    members: dict[int, list[int]] = {}
    for i in range(c):
        members.setdefault(root(i), []).append(i)
    groups = tuple(tuple(m) for m in sorted(members.values()))
    if not reasons:
        reasons = [
            "no one-hot's changes depend on another's code (largest share "
            f"{float(shared.max()) if c > 1 else 0.0:.2f}) or come with another's "
            f"(largest {float(together.max()) if c > 1 else 0.0:.2f}): one graph each"
        ]
    return GroupChoice(groups, shared.float(), together.float(), "; ".join(reasons))
