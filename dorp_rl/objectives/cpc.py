"""CPCLoss: InfoNCE between discrete codes of o_t and o_{t+k}, with in-batch negatives."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from dorp_rl.config import Floats
from dorp_rl.modules.encoder import DiscreteCodeEncoder, pool_blocks
from dorp_rl.modules.similarity import _Similarity
from dorp_rl.validation import check_choice, check_float


def standardize_codes(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """LayerNorm without affine over each one-hot's valid logits (masked stay ``-inf``).

    Args:
        logits: ``[*B, C, Z]`` with ``-inf`` where ``mask`` is True.
        mask: bool ``[C, Z]``, True on codes a one-hot does not have.

    Examples:
        >>> import torch
        >>> from dorp_rl.objectives import standardize_codes
        >>> mask = torch.tensor([[False, False, False], [False, False, True]])  # Z = 3 and 2
        >>> logits = torch.tensor([[[1.0, 2.0, 3.0], [5.0, 7.0, float("-inf")]]])
        >>> standardize_codes(logits, mask)
        tensor([[[-1.2247,  0.0000,  1.2247],
                 [-1.0000,  1.0000,    -inf]]])
    """
    valid = (~mask).to(logits.dtype)
    count = valid.sum(-1, keepdim=True)
    finite = logits.masked_fill(mask, 0.0)
    mean = (finite * valid).sum(-1, keepdim=True) / count
    var = ((finite - mean) ** 2 * valid).sum(-1, keepdim=True) / count
    return ((finite - mean) / (var + 1e-5).sqrt()).masked_fill(mask, float("-inf"))


def change_overlap(change: torch.Tensor) -> torch.Tensor:
    """Mean cosine similarity, over pairs of one-hots, of how much each changes in a batch.

    Args:
        change: non-negative ``[B, C]``, how much one-hot ``c`` changes within pair ``b``.

    Play data move one object per step, so one-hots that each follow one object change
    on disjoint sets of pairs (orthogonal columns, cosine 0), while one-hots that each
    see several objects change together (cosine near 1). The cosine ignores the size of
    the changes, so it cannot be lowered by making everything constant.
    """
    unit = change / change.norm(dim=0, keepdim=True).clamp_min(1e-6)
    gram = unit.transpose(0, 1) @ unit  # [C, C]
    num = change.shape[-1]
    return (gram.sum() - gram.diagonal().sum()) / (num * (num - 1))


def change_imbalance(change: torch.Tensor) -> torch.Tensor:
    """How unevenly one-hots share the changes of a batch: ``1 - H(u) / log C`` in [0, 1].

    Args:
        change: non-negative ``[B, C]``, how much one-hot ``c`` changes within pair ``b``.

    ``u`` is the average over pairs of each pair's change distribution over one-hots.
    When objects move equally often and each one-hot follows one object, ``u`` is uniform
    (0); a one-hot that follows nothing, or one that follows two objects while another
    duplicates a third, makes it uneven. Pairs where nothing changes are skipped.
    """
    total = change.sum(-1, keepdim=True)
    moving = total.squeeze(-1) > 1e-6
    if not moving.any():
        return change.sum() * 0.0
    share = (change[moving] / total[moving]).mean(0)
    entropy = -(share * share.clamp_min(1e-12).log()).sum()
    return 1.0 - entropy / math.log(change.shape[-1])


def uncovered_motion(
    anchor: torch.Tensor,
    future: torch.Tensor,
    anchor_maps: torch.Tensor,
    future_maps: torch.Tensor,
    stride: int = 1,
) -> torch.Tensor:
    """Share of moving pixels that no object map covers, in [0, 1].

    A pixel moves when it differs between the two frames ``[B, 3, H, W]`` of a pair; it
    is covered as much as the highest value any map ``[B, C', h, w]`` takes on it in either
    frame (the object is under its map where it was and where it went). Maps of an encoder
    with ``map_stride`` ``s`` (``stride``) have a cell per ``s x s`` block of pixels
    (``h = ceil(H / s)``): a pixel takes its cell's value, so each cell weighs as many
    times as it has moving pixels.
    """
    moved = (anchor != future).any(-3).to(anchor_maps.dtype)  # [B, H, W]
    moved = pool_blocks(moved.unsqueeze(1), stride, "sum").squeeze(1)  # [B, h, w]
    cover = torch.maximum(anchor_maps, future_maps).amax(-3)  # [B, h, w]
    if moved.shape != cover.shape:
        raise ValueError(
            f"maps of {list(cover.shape[-2:])} cells do not fit frames of "
            f"{list(anchor.shape[-2:])} pixels at map stride {stride}."
        )
    return ((1 - cover) * moved).sum() / moved.sum().clamp_min(1)


def encoder_has_pairs(probs: torch.Tensor) -> bool:
    """Whether codes have at least two one-hots (the exclusivity term needs pairs)."""
    return probs.shape[-2] > 1


class CPCLoss(LossModule):
    """DORP's contrastive loss on discrete codes (InfoNCE, in-batch negatives).

    For a batch of pairs (o_t, o_{t+k}), one side goes through a hard Gumbel-softmax
    (straight-through one-hots) and the other through a plain softmax; the bilinear
    score ``z_i^T W z'_j`` with the similarity matrix ``W`` is divided by the CE
    temperature and every anchor must pick its own future among the batch.

    Args:
        encoder: a :class:`~dorp_rl.modules.DiscreteCodeEncoder`.
        similarity: a similarity module of dimension ``C * Z`` (DDDP, full or identity).
        gumbel_side: ``"positive"`` (default; the authors' release: softmax on the anchor,
            standardised logits then hard Gumbel on the positive, the direction that
            learned codes here) or ``"anchor"`` (the paper's wording: Gumbel on the anchor).
        gumbel_temperature: Gumbel-softmax temperature (the trainer may anneal it).
        ce_temperature: the scores are divided by it. 0.1 learned codes in about 500
            steps on this CPU where 1.0 (the authors') stalled at 3-4 codes.
        exclusivity_weight: weight of an optional term that keeps the object maps of
            different one-hots from changing on the same pairs (see :func:`change_overlap`):
            it makes each map follow one object where plain InfoNCE often settles on maps
            that all show every object. It also adds :func:`change_imbalance`, so that no
            map is left following nothing while another follows two objects.
        usage_weight: weight of an optional code-usage term,
            ``log Z - H(mean anchor probabilities)`` per one-hot, which discourages
            collapse onto a few codes (0 disables it). One number weighs every one-hot;
            a sequence gives one weight per one-hot. The term pulls a one-hot whose
            states are not equally frequent in play (a key lying half the time) to split
            its frequent state and merge rare ones; a weight of 0 leaves that one-hot's
            code usage to the contrastive loss.
        sparsity_weight: weight of an optional term, the mean value of the object maps,
            that drives each map to zero away from its object. In key rooms it shrinks
            what the key and the door leave in the agent's map, which otherwise flips the
            agent's code with the key at the borders of code regions (docs/NOTES.md).
        motion_weight: weight of an optional motion-coverage term
            (:func:`uncovered_motion`): every pixel that changes between the two frames
            of a pair should lie under the object map of a one-hot of more than 2 codes.
            Without it a key-wall agent map held almost nothing on the agent (mean 0.0003
            on its pixel) and its code followed what the key leaves in the map; with it
            the map sits on the agent (docs/NOTES.md, "Key-wall codes").

    Reads ``pixels`` (o_t) and ``future_pixels`` (o_{t+k}) and returns ``loss_cpc`` (plus
    ``loss_usage``, ``loss_exclusivity``, ``loss_sparsity`` and ``loss_motion`` when
    enabled) and detached metrics: ``accuracy`` (share of anchors whose best-scoring candidate is their own
    future), ``mi_lower_bound`` (``log B - loss_cpc``), ``codes_in_batch`` (distinct anchor
    codes per one-hot, averaged), ``min_codes_in_batch`` / ``max_codes_in_batch`` (the
    fewest / most on a one-hot of more than 2 codes), ``similarity_scale``, ``gumbel_temperature``, ``map_mass`` (summed
    object-map values per one-hot, averaged) and, with the exclusivity term,
    ``map_entanglement`` (its unweighted value: near 0 when each map follows one object).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DDDPSimilarity, DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.objectives import CPCLoss
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> loss = CPCLoss(encoder, DDDPSimilarity(16))
        >>> pixels = torch.randint(0, 256, (6, 3, 16, 16), dtype=torch.uint8)
        >>> out = loss(TensorDict(pixels=pixels, future_pixels=pixels, batch_size=[6]))
        >>> out["loss_cpc"].shape, out["loss_cpc"].requires_grad
        (torch.Size([]), True)
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads.

        Attributes:
            pixels: anchor images o_t. Defaults to ``"pixels"``.
            future_pixels: positive images o_{t+k}. Defaults to ``"future_pixels"``.
        """

        pixels: NestedKey = "pixels"
        future_pixels: NestedKey = "future_pixels"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        encoder: DiscreteCodeEncoder,
        similarity: _Similarity,
        *,
        gumbel_side: str = "positive",
        gumbel_temperature: float = 0.1,
        ce_temperature: float = 0.1,
        usage_weight: float | Sequence[float] = 0.0,
        exclusivity_weight: float = 0.0,
        sparsity_weight: float = 0.0,
        motion_weight: float = 0.0,
    ) -> None:
        super().__init__()
        check_choice("gumbel_side", gumbel_side, ("positive", "anchor"))
        dim = encoder.num_onehots * encoder.max_codes
        if similarity.dim != dim:
            raise ValueError(
                f"similarity has dim {similarity.dim}, the encoder's flattened codes have "
                f"{encoder.num_onehots} x {encoder.max_codes} = {dim}."
            )
        self.encoder = encoder
        self.similarity = similarity
        self.gumbel_side = gumbel_side
        positive = {"low": 0.0, "low_open": True}
        self.gumbel_temperature = check_float("gumbel_temperature", gumbel_temperature, **positive)
        self.ce_temperature = check_float("ce_temperature", ce_temperature, **positive)
        self.usage_weight = Floats(low=0.0, allow_scalar=True)("usage_weight", usage_weight)
        weights = torch.as_tensor(self.usage_weight, dtype=torch.float32)
        if weights.dim() and weights.numel() != encoder.num_onehots:
            raise ValueError(
                f"usage_weight has {weights.numel()} weights, the encoder has "
                f"{encoder.num_onehots} one-hots (give one number or one per one-hot)."
            )
        # a plain tensor, not a buffer: the weights are settings, not state to checkpoint
        self._usage_weights = weights.expand(encoder.num_onehots).clone()
        self.exclusivity_weight = check_float("exclusivity_weight", exclusivity_weight, low=0.0)
        self.sparsity_weight = check_float("sparsity_weight", sparsity_weight, low=0.0)
        self.motion_weight = check_float("motion_weight", motion_weight, low=0.0)
        sizes = torch.tensor(encoder.code_sizes)
        self._wide_onehots = (
            sizes > 2 if (sizes > 2).any() else torch.ones_like(sizes, dtype=torch.bool)
        )

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def _hard_gumbel(self, logits: torch.Tensor) -> torch.Tensor:
        normed = standardize_codes(logits, self.encoder.code_mask)
        return F.gumbel_softmax(normed, tau=self.gumbel_temperature, hard=True, dim=-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        anchor = tensordict.get(self.tensor_keys.pixels)
        future = tensordict.get(self.tensor_keys.future_pixels)
        if anchor.shape != future.shape:
            raise ValueError(
                f"{self.tensor_keys.pixels} and {self.tensor_keys.future_pixels} must have the "
                f"same shape, got {list(anchor.shape)} and {list(future.shape)}."
            )
        if anchor.dim() != 4 or anchor.shape[0] < 2:
            raise ValueError(
                "expected a batch of at least 2 pairs of shape [B, "
                f"{', '.join(map(str, getattr(self.encoder, 'frame_shape', 'CHW')))}], "
                f"got {list(anchor.shape)}."
            )
        batch = anchor.shape[0]
        # One pass through the encoder so that BatchNorm sees both sides.
        logits, maps = self.encoder.logits_and_maps(torch.cat([anchor, future]))
        anchor_logits, future_logits = logits[:batch], logits[batch:]
        if self.gumbel_side == "positive":
            z_anchor = anchor_logits.softmax(-1)
            z_future = self._hard_gumbel(future_logits)
        else:
            z_anchor = self._hard_gumbel(anchor_logits)
            z_future = future_logits.softmax(-1)
        scores = self.similarity(z_anchor.flatten(1), z_future.flatten(1)) / self.ce_temperature
        scores = scores - scores.max(dim=1, keepdim=True).values.detach()
        labels = torch.arange(batch, device=scores.device)
        loss_cpc = F.cross_entropy(scores, labels)

        probs = anchor_logits.softmax(-1)
        codes = anchor_logits.argmax(-1)  # [B, C]
        used = torch.tensor(
            [float(torch.unique(codes[:, c]).numel()) for c in range(codes.shape[1])]
        )
        out = TensorDict(
            loss_cpc=loss_cpc,
            accuracy=(scores.argmax(1) == labels).float().mean().detach(),
            mi_lower_bound=(math.log(batch) - loss_cpc).detach(),
            codes_in_batch=used.mean(),
            # 2-way one-hots (key bits) cannot show a collapse: judge the larger ones.
            min_codes_in_batch=used[self._wide_onehots].min(),
            max_codes_in_batch=used[self._wide_onehots].max(),
            gumbel_temperature=torch.tensor(self.gumbel_temperature),
            similarity_scale=self.similarity.matrix().diagonal().mean().detach(),
            batch_size=[],
        )
        if bool((self._usage_weights > 0).any()):
            mean_probs = probs.mean(0).clamp_min(1e-12)  # [C, Z]
            entropy = (
                -(mean_probs * mean_probs.log()).masked_fill(self.encoder.code_mask, 0).sum(-1)
            )
            max_entropy = torch.tensor(self.encoder.code_sizes, dtype=entropy.dtype).log()
            deficit = max_entropy.to(entropy.device) - entropy
            out.set("loss_usage", (self._usage_weights.to(deficit) * deficit).mean())
        if self.sparsity_weight > 0:
            out.set("loss_sparsity", self.sparsity_weight * maps.mean())
        if self.motion_weight > 0:
            # Only the wide one-hots' maps may cover motion: a key bit's map that did
            # took the agent (docs/NOTES.md, "Key-wall codes").
            wide = self._wide_onehots.to(maps.device)
            stride = getattr(self.encoder, "map_stride", 1)
            uncovered = uncovered_motion(
                anchor, future, maps[:batch, wide], maps[batch:, wide], stride=stride
            )
            out.set("loss_motion", self.motion_weight * uncovered)
        out.set("map_mass", maps.detach().flatten(-2).sum(-1).mean())
        if self.exclusivity_weight > 0 and encoder_has_pairs(probs):
            # How much each one-hot's object map changes between o_t and o_t+k: dense
            # gradients straight into the extractor, where objects are told apart.
            map_change = (maps[:batch] - maps[batch:]).abs().flatten(-2).sum(-1)  # [B, C]
            entanglement = change_overlap(map_change) + change_imbalance(map_change)
            out.set("loss_exclusivity", self.exclusivity_weight * entanglement)
            out.set("map_entanglement", entanglement.detach())
        return out
