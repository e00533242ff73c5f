"""The waypoint cost: how far an imagined frame's codes are from a target code
(:class:`CodeMatchCost`), with a penalty per step to prefer early arrival.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import NestedKey, unravel_key
from torch import nn

from dorp_rl.envs.planning import HeldFrames, RolloutFrames
from dorp_rl.modules.encoder import eval_mode
from dorp_rl.planners.costs.base import (
    RolloutCost,
    compact_broadcast,
    get_rollout_frames,
    get_rollout_key,
)
from dorp_rl.planners.costs.caches import EncodingCache
from dorp_rl.planners.rollout import CandidateRollout
from dorp_rl.validation import check_float, check_int

__all__ = [
    "CodeMatchCost",
    "check_step_penalty",
]


#: ``step_penalty`` of :class:`CodeMatchCost` stays below this, so that a match at step 25
#: still costs less than 0.5 (less than a frame that misses the code)
STEP_PENALTY_MAX = 0.02


def check_step_penalty(value: float, name: str = "step_penalty") -> float:
    """``value`` as a finite float in ``[0, STEP_PENALTY_MAX)``, or a ``ValueError`` naming ``name``."""
    try:
        return check_float(name, value, low=0.0, high=STEP_PENALTY_MAX, high_open=True)
    except ValueError as err:
        raise ValueError(f"{err} (so that a match at step 25 still costs less than 0.5)") from None


class CodeMatchCost(RolloutCost):
    """0 once the encoder's code of a predicted frame is the target code, else 1.

    DORP's waypoint cost. At each step the predicted frame is encoded; the step
    *matches* when the chosen one-hots hold the target code (``target_key``, e.g.
    ``subgoal_code``) while every other one-hot keeps its code of the start frame (root
    ``pixels``: the frame the planner started from). Per-step cost::

        (step_penalty * t if match else 1) - tie_break * confidence

    where ``confidence`` is the mean over one-hots of the probability of the wanted code,
    so that among matching sequences (and among failing ones) the more confident win,
    and ``t`` is the step (1..H): with ``step_penalty > tie_break`` a sequence that
    reaches the target earlier wins over one that gets there later, whatever their
    confidence (``"min"`` alone scores both alike, so plans took detours). The cost lies
    in ``[-tie_break, 1]``. ``step_aggregation="min"`` by default: a
    sequence is good if it reaches the target at some step (and open-loop execution
    stops there).

    Args:
        encoder: a :class:`~dorp_rl.modules.DiscreteCodeEncoder` (anything with
            ``encoder(pixels) -> (code [*B, C], probs [*B, C, Z])`` works). It is run in
            eval mode without gradients and its mode is restored after.
        target_key: target code, int64 ``[*B, C]`` in the acting tensordict.
        onehots: which one-hots must reach the target: ``None`` for all of them, a
            sequence of indices, or a key of a bool ``[*B, C]`` mask in the acting
            tensordict (one choice per row, as a batched DORP policy needs).
        pixels_key: the predicted frames in the rollout.
        start_pixels_key: the start frame (a root key, shared by candidates and steps).
        code_key: the predicted codes in the rollout, int64 ``[*B, N, H, C]``, when the
            planning env writes them (a latent world model's code head,
            :class:`~dorp_rl.envs.LatentModelEnv`): then no predicted frame is read or
            encoded (only the start frame, once per row) and there is no confidence
            term. ``None`` (default): the frames under ``pixels_key`` are encoded.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        tie_break: weight of the confidence term; small so it only breaks ties.
        step_penalty: cost per step of a matching frame (e.g. ``2 * tie_break``), so
            that earlier arrival wins; 0 (default) scores every matching step alike
            (docs/NOTES.md has what it did to DORP's steps and success).
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per encoder call (bounds memory).
        cache_size: frames whose codes are kept between calls (0: no cache). The
            cache is emptied whenever the encoder's weights change.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import CodeMatchCost
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> rollout = TensorDict(
        ...     {
        ...         "pixels": frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16),
        ...         "subgoal_code": torch.zeros(2, 1, 1, 2, dtype=torch.int64).expand(2, 5, 4, 2),
        ...         ("next", "pixels"): frames,
        ...     },
        ...     batch_size=(2, 5, 4),
        ... )
        >>> cost = CodeMatchCost(encoder, onehots=[0])(rollout)["cost"]
        >>> cost.shape, bool(((cost > -0.01) & (cost <= 1)).all())
        (torch.Size([2, 5, 4]), True)
    """

    def __init__(
        self,
        encoder: nn.Module,
        target_key: NestedKey = "subgoal_code",
        onehots: Sequence[int] | NestedKey | None = None,
        *,
        pixels_key: NestedKey = ("next", "pixels"),
        start_pixels_key: NestedKey = "pixels",
        code_key: NestedKey | None = None,
        out_key: NestedKey = "cost",
        tie_break: float = 1e-3,
        step_penalty: float = 0.0,
        step_aggregation: str = "min",
        chunk_size: int = 1024,
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(encoder):
            raise ValueError(f"encoder must be callable, got {type(encoder).__name__}.")
        cache_size = check_int("cache_size", cache_size, low=0)
        self.cache = EncodingCache(cache_size)
        self.tie_break = check_float("tie_break", tie_break, low=0.0, high=0.5, high_open=True)
        chunk_size = check_int("chunk_size", chunk_size, low=1)
        self.encoder = encoder
        self.target_key = unravel_key(target_key)
        self.pixels_key = unravel_key(pixels_key)
        self.start_pixels_key = unravel_key(start_pixels_key)
        self.code_key = None if code_key is None else unravel_key(code_key)
        step_penalty = check_step_penalty(step_penalty)
        self.step_penalty = step_penalty
        self.chunk_size = int(chunk_size)
        self.onehots_key: NestedKey | None = None
        self.onehots: list[int] | None = None
        # A key is a string or a tuple of strings (nested); anything else is indices.
        if isinstance(onehots, str) or (
            isinstance(onehots, tuple) and onehots and all(isinstance(i, str) for i in onehots)
        ):
            self.onehots_key = unravel_key(onehots)
        elif onehots is not None:
            self.onehots = self._check_onehots(onehots, encoder)
        predicted = self.pixels_key if self.code_key is None else self.code_key
        in_keys = [predicted, self.start_pixels_key, self.target_key]
        if self.onehots_key is not None:
            in_keys.append(self.onehots_key)
        self.in_keys = in_keys
        self.root_frame_keys = [self.start_pixels_key]

    @staticmethod
    def _check_onehots(onehots: Sequence[int], encoder: nn.Module) -> list[int]:
        """``onehots`` as distinct indices of the encoder's one-hots (its ``code_sizes``)."""
        if isinstance(onehots, (str, bytes)) or not isinstance(onehots, Sequence):
            raise ValueError(
                f"onehots must be None, a sequence of one-hot indices or a mask key, got "
                f"{onehots!r}."
            )
        sizes = getattr(encoder, "code_sizes", None)
        count = len(sizes) if sizes is not None else None
        high = None if count is None else count - 1
        chosen = [check_int(f"onehots[{i}]", v, low=0) for i, v in enumerate(onehots)]
        if not chosen:
            raise ValueError("onehots must name at least one one-hot (or be None for all).")
        if high is not None and any(i > high for i in chosen):
            raise ValueError(
                f"onehots must be indices of the encoder's {count} one-hot(s) (0 to {high}, "
                f"code_sizes {tuple(sizes)}), got {tuple(onehots)}."
            )
        if len(set(chosen)) != len(chosen):
            raise ValueError(f"onehots must name each one-hot once, got {tuple(onehots)}.")
        return chosen

    @torch.no_grad()
    def _encode(self, frames: RolloutFrames) -> tuple[torch.Tensor, torch.Tensor]:
        """Codes ``[*L, C]`` and probabilities ``[*L, C, Z]`` of frames ``[*L, ...]`` (held
        or imagined: of imagined ones only the distinct frames the cache lacks are drawn)."""
        code, prob, inverse = self._encode_distinct(frames)
        if inverse is not None:
            code, prob = code[inverse], prob[inverse]
        lead = frames.shape
        return code.reshape(*lead, code.shape[-1]), prob.reshape(*lead, *prob.shape[-2:])

    @torch.no_grad()
    def _encode_distinct(
        self, frames: RolloutFrames
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Codes ``[m, C]`` and probabilities ``[m, C, Z]`` of the distinct frames, and the
        ``inverse [n]`` from every flat frame to its distinct one (``None``: ``m = n``).
        Imagined frames repeat a lot, within a call and across calls: each distinct frame
        is encoded once, and frames seen in earlier calls not at all."""
        module = self.encoder if isinstance(self.encoder, nn.Module) else None
        with eval_mode(module):
            flat, _, inverse, keys = frames.distinct(draw=False)
            if inverse is None and not callable(flat) and flat.shape[0] > 1:
                # deduplication found two frames sharing a hash: keep them out of the
                # cache, which is keyed by hashes
                code, prob = self._encode_frames(flat)
            else:
                code, prob = self.cache.encode(flat, self._encode_frames, module, keys=keys)
        return code, prob, inverse

    def _encode_frames(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codes, probs = [], []
        for chunk in frames.split(self.chunk_size):
            code, prob = self.encoder(chunk)
            codes.append(code)
            probs.append(prob)
        return torch.cat(codes), torch.cat(probs)

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        name = type(self).__name__
        if rollout.batch_dims < 2:
            raise ValueError(
                f"{name} needs a rollout of batch shape [*B, N, H], got {list(rollout.batch_size)}."
            )
        if self.code_key is not None:
            return self._cost_of_predicted_codes(rollout)
        frames = get_rollout_frames(rollout, self.pixels_key, name)
        start = get_rollout_key(rollout, self.start_pixels_key, name)
        target = get_rollout_key(rollout, self.target_key, name)
        if target.dtype.is_floating_point or target.dtype == torch.bool:
            raise ValueError(f"{self.target_key!r} must hold integer codes, got {target.dtype}.")
        # All candidates and steps share the start frame: encode it once per row.
        start_code = self._encode(HeldFrames(start[..., :1, :1, :, :, :]))[0]  # [*B, 1, 1, C]
        # Codes and probabilities of the distinct frames, [m, C] and [m, C, Z]: the
        # [*B, N, H, C, Z] probabilities are never materialised (see below).
        code, distinct_probs, inverse = self._encode_distinct(frames)
        lead = frames.shape
        if inverse is None:
            code = code.reshape(*lead, code.shape[-1])
            probs = distinct_probs.reshape(*lead, *distinct_probs.shape[-2:])
        else:
            code = code[inverse].reshape(*lead, code.shape[-1])
        num_onehots = code.shape[-1]
        if target.shape[-1] != num_onehots:
            raise ValueError(
                f"{self.target_key!r} must have {num_onehots} codes (one per one-hot), "
                f"got shape {list(target.shape)}."
            )
        chosen = self._chosen(rollout, num_onehots, code.device)
        num_codes = distinct_probs.shape[-1]
        self._check_target(target, chosen, num_codes)
        wanted = torch.where(chosen, target.to(code.device), start_code)  # [*B, N, H, C]
        if inverse is not None and bool(((wanted < 0) | (wanted >= num_codes)).any()):
            # Out-of-range codes: let gather refuse them as on the drawn path.
            probs = distinct_probs[inverse].reshape(*code.shape, num_codes)
            inverse = None
        wanted = wanted.expand_as(code)
        match = (code == wanted).all(-1)
        if inverse is None:
            picked = probs.gather(-1, wanted.unsqueeze(-1)).squeeze(-1)
        else:
            # The same entries as gathering from distinct_probs[inverse], read in place.
            flat_wanted = wanted.reshape(-1, num_onehots)
            onehot = torch.arange(num_onehots, device=code.device)
            index = (inverse.unsqueeze(-1) * num_onehots + onehot) * num_codes + flat_wanted
            picked = distinct_probs.reshape(-1)[index].reshape(code.shape)
        confidence = picked.mean(-1)
        cost = (~match).to(torch.float32) - self.tie_break * confidence.to(torch.float32)
        if self.step_penalty:
            steps = torch.arange(1, cost.shape[-1] + 1, device=cost.device, dtype=cost.dtype)
            cost = cost + self.step_penalty * steps * match.to(cost.dtype)
        return cost

    def _chosen(self, rollout: CandidateRollout, num_onehots: int, device: Any) -> torch.Tensor:
        """Bool mask of the one-hots that must reach the target (per row, or fixed)."""
        if self.onehots_key is not None:
            name = type(self).__name__
            return get_rollout_key(rollout, self.onehots_key, name).to(torch.bool)
        chosen = torch.zeros(num_onehots, dtype=torch.bool, device=device)
        chosen[self.onehots if self.onehots is not None else slice(None)] = True
        return chosen

    def _cost_of_predicted_codes(self, rollout: CandidateRollout) -> torch.Tensor:
        """Per-step costs from the codes the planning env predicted (``code_key``)."""
        name = type(self).__name__
        code = get_rollout_key(rollout, self.code_key, name)
        start = get_rollout_key(rollout, self.start_pixels_key, name)
        target = get_rollout_key(rollout, self.target_key, name)
        if code.dtype.is_floating_point or target.dtype.is_floating_point:
            raise ValueError(
                f"{self.code_key!r} and {self.target_key!r} must hold integer codes, got "
                f"{code.dtype} and {target.dtype}."
            )
        start_code = self._encode(HeldFrames(start[..., :1, :1, :, :, :]))[0]  # [*B, 1, 1, C]
        num_onehots = code.shape[-1]
        if target.shape[-1] != num_onehots or start_code.shape[-1] != num_onehots:
            raise ValueError(
                f"the planning env predicts {num_onehots} codes per frame under "
                f"{self.code_key!r}; the encoder gives {start_code.shape[-1]} and "
                f"{self.target_key!r} holds {target.shape[-1]}: the world model was trained "
                "on another encoder's codes."
            )
        chosen = self._chosen(rollout, num_onehots, code.device)
        wanted = torch.where(chosen, target.to(code.device), start_code.to(code.device))
        match = (code == wanted.expand_as(code)).all(-1)
        cost = (~match).to(torch.float32)
        if self.step_penalty:
            steps = torch.arange(1, cost.shape[-1] + 1, device=cost.device, dtype=cost.dtype)
            cost = cost + self.step_penalty * steps * match.to(cost.dtype)
        return cost

    def _check_target(self, target: torch.Tensor, chosen: torch.Tensor, max_codes: int) -> None:
        """Refuses a target code outside its one-hot's codes (on the broadcast rows only)."""
        sizes = getattr(self.encoder, "code_sizes", None) or (max_codes,) * target.shape[-1]
        sizes = torch.as_tensor(sizes, device=target.device)
        chosen = compact_broadcast(chosen.to(target.device).expand_as(target), keep_last=1)
        target = compact_broadcast(target, keep_last=1)
        bad = ((target < 0) | (target >= sizes)) & chosen
        target = target.expand_as(bad)
        if bad.any():
            index = bad.nonzero()[0].tolist()
            onehot = index[-1]
            raise ValueError(
                f"{self.target_key!r} holds code {int(target[tuple(index)])} for one-hot "
                f"{onehot}, which has {int(sizes[onehot])} codes (valid: 0 to "
                f"{int(sizes[onehot]) - 1})."
            )

    def extra_repr(self) -> str:
        which = self.onehots_key if self.onehots_key is not None else self.onehots
        return f"target_key={self.target_key!r}, onehots={which!r}, {super().extra_repr()}"
