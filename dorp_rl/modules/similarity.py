"""Similarity matrices of the bilinear InfoNCE score ``z_anchor^T W z_positive``.

- :class:`DDDPSimilarity`: DORP's diagonally dominant, diagonally positive matrix;
- :class:`FullSimilarity`: an arbitrary learned matrix (CPC's ablation);
- :class:`IdentitySimilarity`: the identity (MoCo-style ablation).

Each is an ``nn.Module`` whose :meth:`matrix` returns ``W`` ``[L, L]`` for codes
flattened to length ``L = C * Z``; calling it on ``(anchor [B, L], positive [B', L])``
gives the score matrix ``[B, B']``.
"""

from __future__ import annotations

import torch
from torch import nn

from dorp_rl.validation import check_choice, check_float, check_int


class _Similarity(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = check_int("dim", dim, low=1)

    def matrix(self) -> torch.Tensor:
        raise NotImplementedError

    @torch.no_grad()
    def permute_(self, index: torch.Tensor) -> None:
        """Reorders the code positions of every ``[L, L]`` parameter, rows and columns alike:
        position ``i`` takes what position ``index[i]`` had (``index`` int ``[L]``)."""
        index = torch.as_tensor(index, dtype=torch.long)
        if sorted(index.tolist()) != list(range(self.dim)):
            raise ValueError(
                f"index must be a permutation of range({self.dim}), got {index.tolist()}."
            )
        for parameter in self.parameters():
            if parameter.shape == (self.dim, self.dim):
                index = index.to(parameter.device)
                parameter.copy_(parameter[index][:, index])

    def forward(self, anchor: torch.Tensor, positive: torch.Tensor) -> torch.Tensor:
        """Scores ``[B, B']`` of every anchor ``[B, L]`` against every candidate ``[B', L]``."""
        for name, value in (("anchor", anchor), ("positive", positive)):
            if value.dim() != 2 or value.shape[-1] != self.dim:
                raise ValueError(
                    f"{name} must have shape [B, {self.dim}], got {list(value.shape)}."
                )
        return anchor @ self.matrix() @ positive.transpose(0, 1)


class DDDPSimilarity(_Similarity):
    """DORP's matrix ``exp(psi0) * (-sigmoid(psi1) + alpha * I)``.

    For ``alpha >= 1`` and any parameters, every diagonal entry is positive and larger
    than every other entry of its row and column (off-diagonal entries are negative),
    which pushes a code to score highest against itself: temporally close frames share
    codes, and neighbouring codes can learn milder penalties than distant ones.

    Args:
        dim: flattened code length ``L``.
        alpha: the diagonal offset (the authors used 1).
        sign: ``"paper"`` for the formula above, or ``"authors"`` for their release:
            ``exp(psi0) * (sigmoid(psi1) + alpha)`` on the diagonal and
            ``-exp(psi0) * sigmoid(psi1)`` off it.
        init_scale: initial ``exp(psi0)``.

    Examples:
        >>> import torch
        >>> from dorp_rl.modules import DDDPSimilarity
        >>> w = DDDPSimilarity(8).matrix()
        >>> off_diagonal = w[~torch.eye(8, dtype=torch.bool)]
        >>> bool((w.diagonal() > 0).all()), bool((off_diagonal < 0).all())
        (True, True)
    """

    def __init__(
        self, dim: int, alpha: float = 1.0, sign: str = "paper", init_scale: float = 1.0
    ) -> None:
        super().__init__(dim)
        self.sign = check_choice("sign", sign, ("paper", "authors"))
        self.alpha = check_float("alpha", alpha, low=1.0)  # >= 1: diagonally dominant
        init_scale = check_float("init_scale", init_scale, low=0.0, low_open=True)
        self.log_scale = nn.Parameter(torch.tensor(float(init_scale)).log())
        self.psi = nn.Parameter(torch.zeros(self.dim, self.dim))

    def matrix(self) -> torch.Tensor:
        scale = self.log_scale.exp()
        eye = torch.eye(self.dim, dtype=torch.bool, device=self.psi.device)
        off = -torch.sigmoid(self.psi)
        if self.sign == "paper":
            # alpha - sigmoid(x) written as (alpha - 1) + sigmoid(-x): stays > 0 in float32.
            diag = (self.alpha - 1.0) + torch.sigmoid(-self.psi)
        else:
            diag = self.alpha + torch.sigmoid(self.psi)
        return scale * torch.where(eye, diag, off)


class FullSimilarity(_Similarity):
    """An arbitrary learned matrix (CPC), initialised to the identity plus small noise.

    Examples:
        >>> from dorp_rl.modules import FullSimilarity
        >>> FullSimilarity(8).matrix().shape
        torch.Size([8, 8])
    """

    def __init__(self, dim: int, init_noise: float = 0.01) -> None:
        super().__init__(dim)
        self.weight = nn.Parameter(
            torch.eye(self.dim) + init_noise * torch.randn(self.dim, self.dim)
        )

    def matrix(self) -> torch.Tensor:
        return self.weight


class IdentitySimilarity(_Similarity):
    """The identity: the score counts matching codes (MoCo-style dot product).

    Examples:
        >>> import torch
        >>> from dorp_rl.modules import IdentitySimilarity
        >>> bool(torch.equal(IdentitySimilarity(4).matrix(), torch.eye(4)))
        True
    """

    def __init__(self, dim: int) -> None:
        super().__init__(dim)
        self.register_buffer("eye", torch.eye(self.dim), persistent=False)

    def matrix(self) -> torch.Tensor:
        return self.eye


SIMILARITIES = {"dddp": DDDPSimilarity, "full": FullSimilarity, "identity": IdentitySimilarity}


def make_similarity(kind: str, dim: int, **kwargs) -> _Similarity:
    """Builds a similarity by name: ``"dddp"``, ``"full"`` or ``"identity"``.

    Examples:
        >>> from dorp_rl.modules import make_similarity
        >>> make_similarity("dddp", 8, alpha=2.0).alpha, make_similarity("full", 8).matrix().shape
        (2.0, torch.Size([8, 8]))
    """
    if kind not in SIMILARITIES:
        raise ValueError(f"similarity must be one of {sorted(SIMILARITIES)}, got {kind!r}.")
    return SIMILARITIES[kind](dim, **kwargs)
