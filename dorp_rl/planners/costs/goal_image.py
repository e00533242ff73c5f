"""Costs of an imagined frame against the goal image: its blurred pixel distance
(:class:`PixelDistanceCost`), the distance of its object maps (:class:`ObjectMapCost`)
and, through a latent model, of its latent (:class:`LatentGoalCost`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import NestedKey, unravel_key
from torch import nn

from dorp_rl.envs.planning import row_hashes
from dorp_rl.modules.encoder import eval_mode
from dorp_rl.planners.costs.base import (
    RolloutCost,
    compact_broadcast,
    get_rollout_frames,
    get_rollout_key,
)
from dorp_rl.planners.costs.caches import KeyedCache
from dorp_rl.planners.rollout import CandidateRollout
from dorp_rl.validation import check_float, check_int

__all__ = [
    "LatentGoalCost",
    "ObjectMapCost",
    "PixelDistanceCost",
]


#: Joins a frame's and a goal's row hashes into the key of the pair (an odd 64-bit factor).
_PAIR_KEY_FACTOR = 0x9E3779B97F4A7C15 - 2**64


class _GoalFrameCost(RolloutCost):
    """A cost of each predicted frame against the goal image (the shared keys and blurs)."""

    def _set_frame_keys(
        self,
        goal_key: NestedKey,
        pixels_key: NestedKey,
        chunk_size: int,
        blur_sigmas: Sequence[float],
        cache_size: int,
    ) -> None:
        self.chunk_size = check_int("chunk_size", chunk_size, low=1)
        self.blur_sigmas = _register_blurs(self, blur_sigmas)
        self.goal_key = unravel_key(goal_key)
        self.pixels_key = unravel_key(pixels_key)
        self.in_keys = [self.pixels_key, self.goal_key]
        self.root_frame_keys = [self.goal_key]
        self.cache = KeyedCache(check_int("cache_size", cache_size, low=0))

    def _pair_costs(
        self,
        frames: torch.Tensor,
        goals: torch.Tensor,
        owner: torch.Tensor,
        compute: Callable[[torch.Tensor], torch.Tensor],
        module: nn.Module | None = None,
        cached: bool = True,
    ) -> torch.Tensor:
        """Costs ``[m]`` of the (frame, goal) pairs ``frames[i]``, ``goals[owner[i]]``:
        ``compute(indices)`` for the pairs not scored in an earlier call (the goal phase
        plans from nearly the same state many times), the others from the cache.
        ``cached=False`` computes them all: deduplication found two frames sharing a hash,
        which the cache, keyed by hashes, would confuse."""
        if (
            not cached
            or self.cache.size == 0
            or frames.dtype != torch.uint8
            or frames.shape[0] == 0
        ):
            return compute(torch.arange(frames.shape[0], device=frames.device))
        goal_keys = row_hashes(goals).index_select(0, owner)
        keys = row_hashes(frames) * _PAIR_KEY_FACTOR + goal_keys  # wraps modulo 2**64
        return self.cache.fetch(keys, lambda miss: (compute(miss),), module)[0]

    def extra_repr(self) -> str:
        blur = f", blur_sigmas={self.blur_sigmas}" if self.blur_sigmas else ""
        return f"goal_key={self.goal_key!r}{blur}, {super().extra_repr()}"


class PixelDistanceCost(_GoalFrameCost):
    """L2 distance between each predicted frame and the goal image (the paper's VF cost).

    Per step: ``|| next_pixels / 255 - goal / 255 ||_2`` over the 768 values of the frame
    (0 when the predicted frame is the goal, about 4.9 for one 2x4 block of a saturated
    colour moved by one cell). ``step_aggregation="min"`` by default: a candidate is
    scored by the closest it gets to the goal.

    Plain L2 is flat once a block no longer overlaps its place in the goal image: moving
    it closer changes nothing until it touches. ``blur_sigmas`` adds the L2 distance of
    the frames blurred with a Gaussian of each given width (in cells), which keeps
    decreasing as a block approaches from further away.

    Args:
        goal_key: the goal image, uint8 ``[*B, C, H, W]`` in the acting tensordict.
        pixels_key: the predicted frames in the rollout.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per chunk of the computation (a speed knob, not a result one).
        blur_sigmas: widths of the extra blurred terms (default none: the paper's L2).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import PixelDistanceCost
        >>> goal = torch.zeros(2, 1, 1, 3, 16, 16, dtype=torch.uint8).expand(2, 5, 4, 3, 16, 16)
        >>> frames = torch.zeros(2, 5, 4, 3, 16, 16, dtype=torch.uint8)
        >>> rollout = TensorDict(
        ...     {"goal_pixels": goal, ("next", "pixels"): frames}, batch_size=(2, 5, 4)
        ... )
        >>> PixelDistanceCost()(rollout)["cost"].shape
        torch.Size([2, 5, 4])
    """

    def __init__(
        self,
        goal_key: NestedKey = "goal_pixels",
        pixels_key: NestedKey = ("next", "pixels"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
        chunk_size: int = 512,
        blur_sigmas: Sequence[float] = (),
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        self._set_frame_keys(goal_key, pixels_key, chunk_size, blur_sigmas, cache_size)

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        """The costs. Without ``blur_sigmas``, frames that can give their exact squared
        distances without being drawn (lazy :class:`~dorp_rl.envs.planning.ImaginedFrames`
        of an env whose frames are sums of parts) do, when each is an integer below
        ``2**24`` (checked), which float32 holds exactly whatever the summation order; the
        blurred terms are computed on the distinct (frame, goal) pairs, of which only the
        distinct frames are drawn.
        """
        pairs = _GoalPairs(rollout, self.pixels_key, self.goal_key, type(self).__name__)
        goals = pairs.goals.reshape(pairs.goals.shape[0], -1).to(torch.float32)
        if not self.blur_sigmas:
            goal_rows = pairs.goals.reshape(goals.shape)
            squared = pairs.frames.squared_distances(goal_rows, pairs.owner)
            if squared is not None and (squared.numel() == 0 or int(squared.max()) < 2**24):
                # Exactly what the float loop below gives: every partial sum of the
                # squared differences is an integer below 2**24, which float32 holds.
                return squared.to(torch.float32).sqrt_().div_(255.0).reshape(pairs.lead)
        # Blurring costs ~50x the plain distance; imagined frames repeat a lot, so
        # score each distinct (frame, goal) pair once.
        frames, owner, inverse = pairs.distinct(dedupe=bool(self.blur_sigmas))
        frame_shape = pairs.frame_shape

        def compute(index: torch.Tensor) -> torch.Tensor:
            rows = frames.reshape(frames.shape[0], -1).index_select(0, index)
            out = torch.empty(rows.shape[0], dtype=torch.float32, device=rows.device)
            # Chunks of a few hundred frames stay in cache: ~10x faster than one pass.
            for start in range(0, rows.shape[0], self.chunk_size):
                stop = start + self.chunk_size
                diff = rows[start:stop].to(torch.float32)
                diff.sub_(goals.index_select(0, owner[index[start:stop]]))
                total = diff.square().sum(-1).sqrt_()
                for i in range(len(self.blur_sigmas)):
                    # Blurring is linear: the blurred frames differ by the blurred difference.
                    blurred = _blur(diff.view(-1, *frame_shape), getattr(self, f"_blur{i}"))
                    total += blurred.flatten(1).square().sum(-1).sqrt_()
                out[start:stop] = total
            return out

        if self.blur_sigmas:
            out = self._pair_costs(frames, pairs.goals, owner, compute, cached=inverse is not None)
        else:  # plain distances cost less than the cache's hashing
            out = compute(torch.arange(frames.shape[0], device=frames.device))
        if inverse is not None:
            out = out[inverse]
        return out.div_(255.0).reshape(pairs.lead)


def _blur(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of ``[n, c, h, w]`` images, mirrored at the borders.

    Mirroring (each border cell repeated once, then the image backwards) keeps every
    cell's mass inside the frame: with zero padding a block in a corner loses part of
    its blurred mass, so its distance to any far goal shrinks and pixel-distance
    planners drift into corners. The blur is linear, so it is two small matrix
    products, ``rows @ image @ cols.T``, with the mirroring folded into the matrices
    (several times faster than padded convolutions on 16 x 16 frames).
    """
    rows = _blur_matrix(taps, images.shape[-2]).to(images.dtype)
    cols = _blur_matrix(taps, images.shape[-1]).to(images.dtype)
    return torch.matmul(torch.matmul(rows, images), cols.transpose(0, 1))


def _blur_matrix(taps: torch.Tensor, size: int) -> torch.Tensor:
    """``[size, size]`` matrix of a 1-D blur with ``taps``, mirrored at both ends."""
    radius = taps.shape[0] // 2
    source = torch.arange(size, device=taps.device).unsqueeze(1) + torch.arange(
        -radius, radius + 1, device=taps.device
    )
    # Mirrored as often as needed (period 2 * size): a blur wider than a small frame
    # folds back into it and keeps all of its mass.
    source = source.remainder(2 * size)
    source = torch.where(source >= size, 2 * size - 1 - source, source)
    matrix = torch.zeros(size, size, dtype=taps.dtype, device=taps.device)
    return matrix.scatter_add_(1, source, taps.expand(size, -1).contiguous())


class _GoalPairs:
    """The (frame, goal) pairs of a rollout that a distance to the goal image scores.

    ``goals`` uint8 ``[G, *frame_shape]`` holds one copy per distinct goal (the goal is
    a broadcast view: it is never materialised ``N * H`` times) and ``owner [n]`` maps
    each of the ``n`` flat steps to its goal; ``lead`` is the rollout's ``[*B, N, H]``.
    """

    def __init__(
        self, rollout: CandidateRollout, pixels_key: NestedKey, goal_key: NestedKey, name: str
    ) -> None:
        self.frames = get_rollout_frames(rollout, pixels_key, name)
        self.frame_shape, self.lead = self.frames.frame_shape, self.frames.shape
        goal = get_rollout_key(rollout, goal_key, name)
        if tuple(self.frame_shape) != tuple(goal.shape[-3:]):
            raise ValueError(
                f"{goal_key!r} must have the frame shape of {pixels_key!r} "
                f"({list(self.frame_shape)}), got {list(goal.shape)}."
            )
        goal = compact_broadcast(goal.expand(*self.lead, *goal.shape[-3:]), keep_last=3)
        self.goals = goal.reshape(-1, *self.frame_shape)
        owner = torch.arange(self.goals.shape[0], device=goal.device).reshape(goal.shape[:-3])
        self.owner = owner.expand(self.lead).reshape(-1)

    def distinct(
        self, dedupe: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(frames [m, *frame_shape], owner [m], inverse [n] | None)``: with ``dedupe``,
        each distinct (frame, goal) pair once (imagined frames: only those are drawn),
        and ``inverse`` from every step to its pair (``None``: every step, in order)."""
        if not dedupe:
            return self.frames.pixels().reshape(-1, *self.frame_shape), self.owner, None
        frames, owner, inverse, _ = self.frames.distinct(self.owner.unsqueeze(-1))
        return frames, owner.squeeze(-1), inverse


class LatentGoalCost(RolloutCost):
    """Distance of each imagined latent to the goal image's latent, in a latent world model.

    For planning envs that imagine latent states (:class:`~dorp_rl.envs.LatentModelEnv`
    writes ``("next", "latent")``): the goal image is encoded once per row by
    ``model.encode`` (the latent a real frame gets, which the model's dynamics are
    trained to reach) and each step costs the root mean square of the difference,
    ``|| latent - goal_latent ||_2 / sqrt(D)``. So the goal-image phase is judged in the
    model's own latent space, where a few pixels that matter (an agent's heading, say)
    are as visible as they are to the model's encoder, and no frame is decoded.

    Args:
        model: anything with ``encode(pixels [*B, C, H, W]) -> [*B, D]`` (a
            :class:`~dorp_rl.modules.LatentWorldModel`; a module is kept as a submodule).
        goal_key: the goal image, uint8 ``[*B, C, H, W]`` in the acting tensordict.
        latent_key: the imagined latents in the rollout, float ``[*B, N, H, D]``.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import LatentModelConfig, LatentWorldModel
        >>> from dorp_rl.planners import LatentGoalCost
        >>> model = LatentWorldModel(4, LatentModelConfig(frame_shape=(1, 8, 8), code_sizes=(4,)))
        >>> goal = torch.zeros(2, 1, 1, 1, 8, 8, dtype=torch.uint8).expand(2, 5, 3, 1, 8, 8)
        >>> latent = model.encode(torch.zeros(1, 8, 8, dtype=torch.uint8)).detach().expand(2, 5, 3, -1)
        >>> rollout = TensorDict({"goal_pixels": goal, ("next", "latent"): latent}, batch_size=(2, 5, 3))
        >>> cost = LatentGoalCost(model)(rollout)["cost"]
        >>> cost.shape, float(cost.abs().max()) < 1e-5  # every step is at the goal's latent
        (torch.Size([2, 5, 3]), True)
    """

    def __init__(
        self,
        model: Any,
        goal_key: NestedKey = "goal_pixels",
        latent_key: NestedKey = ("next", "latent"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(getattr(model, "encode", None)):
            raise ValueError(
                f"model must have encode(pixels) -> latents (a LatentWorldModel); "
                f"{type(model).__name__} has none."
            )
        self.model = model
        self.goal_key = unravel_key(goal_key)
        self.latent_key = unravel_key(latent_key)
        self.in_keys = [self.latent_key, self.goal_key]
        self.root_frame_keys = [self.goal_key]

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        name = type(self).__name__
        latent = get_rollout_key(rollout, self.latent_key, name)
        lead = latent.shape[:-1]
        goal = get_rollout_key(rollout, self.goal_key, name)
        frame = tuple(getattr(self.model, "frame_shape", goal.shape[-3:]))
        if goal.dim() != len(lead) + 3 or tuple(goal.shape[-3:]) != frame:
            raise ValueError(
                f"{self.goal_key!r} must be frames {list(frame)} over the rollout's "
                f"{list(lead)}, got {list(goal.shape)}."
            )
        # The goal is a broadcast view: encode each distinct row's goal once.
        goal = compact_broadcast(goal.expand(*lead, *frame), keep_last=3)
        with torch.no_grad():
            target = self.model.encode(goal)  # [*compact lead, D]
        if target.shape[-1] != latent.shape[-1]:
            raise ValueError(
                f"the goal's latent has width {target.shape[-1]} but {self.latent_key!r} has "
                f"{latent.shape[-1]}: the model is not the planning env's."
            )
        diff = latent.to(torch.float32) - target.to(torch.float32)
        return diff.square().mean(-1).sqrt()

    def extra_repr(self) -> str:
        return f"goal_key={self.goal_key!r}, latent_key={self.latent_key!r}, {super().extra_repr()}"


class ObjectMapCost(_GoalFrameCost):
    """Distance of each object's map in the predicted frames to its map in the goal image.

    The encoder's object extractor gives one map per one-hot (``encoder.object_maps``,
    float ``[*B, K, H, W]``; with DORP's codes, one object each). Per step::

        sum_k ( ||m_k - g_k||_2 + sum_s ||blur_s(m_k - g_k)||_2 )

    over the maps ``m_k`` of the predicted frame and ``g_k`` of the goal image. Each
    object has its own term, so moving one object towards its goal place never pays for
    another: pixel distance trades objects off (two blocks each in the other's goal place
    are a local minimum for it, since a block stepping aside first makes the frame differ
    from the goal in more cells), object maps do not. The goal-image phase of
    :class:`~dorp_rl.policies.AbstractGoalPolicy` adds it to the pixel distance.

    Args:
        encoder: anything with ``object_maps(pixels) -> [*B, K, H, W]``
            (:class:`~dorp_rl.modules.DiscreteCodeEncoder`); run in eval mode without
            gradients, its mode restored after.
        goal_key: the goal image in the acting tensordict.
        pixels_key: the predicted frames in the rollout.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per encoder call (bounds memory).
        blur_sigmas: widths of the blurred terms, in cells (as :class:`PixelDistanceCost`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import ObjectMapCost
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> goal = frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16)
        >>> rollout = TensorDict(
        ...     {"goal_pixels": goal, ("next", "pixels"): frames}, batch_size=(2, 5, 4)
        ... )
        >>> cost = ObjectMapCost(encoder, blur_sigmas=(2.0,))(rollout)["cost"]
        >>> cost.shape, float(cost[0, 0, 0])
        (torch.Size([2, 5, 4]), 0.0)
    """

    def __init__(
        self,
        encoder: nn.Module,
        goal_key: NestedKey = "goal_pixels",
        pixels_key: NestedKey = ("next", "pixels"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
        chunk_size: int = 1024,
        blur_sigmas: Sequence[float] = (),
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(getattr(encoder, "object_maps", None)):
            raise ValueError(
                f"ObjectMapCost needs an encoder with object_maps(pixels) -> [*B, K, H, W] "
                f"(a DiscreteCodeEncoder), got {type(encoder).__name__}, which has none."
            )
        self.encoder = encoder
        self._set_frame_keys(goal_key, pixels_key, chunk_size, blur_sigmas, cache_size)

    @torch.no_grad()
    def _maps(self, frames: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.encoder.object_maps(c) for c in frames.split(self.chunk_size)])

    @torch.no_grad()
    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        pairs = _GoalPairs(rollout, self.pixels_key, self.goal_key, type(self).__name__)
        frames, owner, inverse = pairs.distinct()
        module = self.encoder if isinstance(self.encoder, nn.Module) else None
        with eval_mode(module):
            goal_maps = self._maps(pairs.goals).to(torch.float32)

            def compute(index: torch.Tensor) -> torch.Tensor:
                out = torch.empty(index.shape[0], dtype=torch.float32, device=goal_maps.device)
                for start in range(0, index.shape[0], self.chunk_size):
                    chunk = index[start : start + self.chunk_size]
                    diff = self._maps(frames.index_select(0, chunk)).to(torch.float32)
                    diff.sub_(goal_maps.index_select(0, owner.index_select(0, chunk)))
                    total = diff.flatten(2).square().sum(-1).sqrt_().sum(-1)
                    for i in range(len(self.blur_sigmas)):
                        blurred = _blur(diff, getattr(self, f"_blur{i}"))
                        total += blurred.flatten(2).square().sum(-1).sqrt_().sum(-1)
                    out[start : start + chunk.shape[0]] = total
                return out

            out = self._pair_costs(
                frames, pairs.goals, owner, compute, module, cached=inverse is not None
            )
        if inverse is not None:
            out = out[inverse]
        return out.reshape(pairs.lead)


def _register_blurs(module: nn.Module, blur_sigmas: Sequence[float]) -> tuple[float, ...]:
    """Checks ``blur_sigmas`` and registers the Gaussian taps of each as ``_blur{i}``."""
    if isinstance(blur_sigmas, (str, bytes)) or not isinstance(blur_sigmas, Sequence):
        raise ValueError(f"blur_sigmas must be a sequence of positive widths, got {blur_sigmas!r}.")
    sigmas = [
        check_float(f"blur_sigmas[{i}]", x, low=0.0, low_open=True)
        for i, x in enumerate(blur_sigmas)
    ]
    for i, sigma in enumerate(sigmas):
        radius = min(15, math.ceil(3 * sigma))
        taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1) / sigma) ** 2)
        module.register_buffer(f"_blur{i}", taps / taps.sum(), persistent=False)
    return tuple(sigmas)
