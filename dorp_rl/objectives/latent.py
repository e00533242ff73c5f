"""LatentWorldModelLoss: a latent world model learns a DORP encoder's codes open loop."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

from dorp_rl.frames import frames_to_unit_float
from dorp_rl.modules.encoder import eval_mode, module_device
from dorp_rl.modules.latent import LatentWorldModel, check_latent_model
from dorp_rl.validation import MissingKeyError, check_bool, check_float, check_int

__all__ = ["LatentWorldModelLoss"]


class LatentWorldModelLoss(LossModule):
    """Trains a :class:`~dorp_rl.modules.LatentWorldModel` on ``[B, H]`` play windows.

    The model encodes the window's first frame o_t and steps its latent with the
    window's actions, restarting from the encoded true frame every ``open_loop_length``
    steps (``None``: one open-loop rollout over the whole window). At every step, the
    code head's logits are scored against the codes the DORP ``code_encoder`` (frozen)
    gives the true frame, so that the imagined codes agree with the encoder on real
    frames (``loss_code``: cross-entropy summed over one-hots; with ``soft_targets``
    against the encoder's probabilities instead of its codes, so that the head learns
    where the encoder is unsure, at the borders of its codes, plus ``hard_weight`` times
    the cross-entropy against its codes, which still picks the encoder's code where its
    probabilities are nearly tied); with a decoder, the decoded frame against the true
    frame (``loss_pixels``: mean squared error on ``[0, 1]`` values, times
    ``pixel_weight``) and, with ``change_weight``, the same error at the values that
    differ from the true frame one step before, averaged over those values alone
    (``loss_change``: a block's one-pixel move changes a dozen of hundreds of values,
    too few for the whole frame's error to make the dynamics learn it), both on
    ``pixel_steps`` random steps of each window or on all (decoding is the largest part
    of a training step); and the imagined latent against the encoded true frame, without
    gradient into the target (``loss_latent``, times ``latent_weight``: squared distance,
    or for a categorical latent the cross-entropy of each imagined variable against the
    true frame's), which keeps imagined latents where real frames put them.

    Reads ``pixels`` ``[B, H, C, H', W']`` (o_t is ``pixels[:, 0]``), ``action``
    ``[B, H, 1]`` (int indices) and ``("next", "pixels")``, e.g. a
    :class:`~dorp_rl.data.SequenceSampler` sample. Detached metrics: ``code_accuracy``
    (share of imagined steps whose every code is the encoder's), ``code_accuracy_last``
    (the window's last step) and ``pixel_error`` (mean absolute error on [0, 1]).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import EncoderConfig, DiscreteCodeEncoder
        >>> from dorp_rl.modules import LatentModelConfig, LatentWorldModel
        >>> from dorp_rl.objectives import LatentWorldModelLoss
        >>> codes = DiscreteCodeEncoder(EncoderConfig.small((4,), frame_shape=(1, 8, 8)))
        >>> model = LatentWorldModel(3, LatentModelConfig(frame_shape=(1, 8, 8), code_sizes=(4,)))
        >>> frames = torch.zeros(2, 5, 1, 8, 8, dtype=torch.uint8)
        >>> td = TensorDict(pixels=frames, action=torch.zeros(2, 5, 1, dtype=torch.int64),
        ...                 next=TensorDict(pixels=frames, batch_size=[2, 5]), batch_size=[2, 5])
        >>> sorted(k for k in LatentWorldModelLoss(model, codes)(td).keys() if k.startswith("loss_"))
        ['loss_code', 'loss_latent', 'loss_pixels']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads.

        Attributes:
            pixels: frames o_t .. o_{t+H-1}, ``[B, H, C, H', W']``. Defaults to ``"pixels"``.
            action: actions a_t .. a_{t+H-1}, int64 ``[B, H, 1]``. Defaults to ``"action"``.
            next_pixels: frames o_{t+1} .. o_{t+H}. Defaults to ``("next", "pixels")``.
            code, next_code: the code encoder's codes of those frames, int64 ``[B, H, K]``,
                if computed beforehand (a trainer encodes its play data once); the
                frames are encoded when they are missing. Default ``"code"`` and
                ``("next", "code")``.
            code_probs, next_code_probs: the code encoder's probabilities of those
                frames, float ``[B, H, K, Z]``, if computed beforehand (read with
                ``soft_targets`` only). Default ``"code_probs"`` and
                ``("next", "code_probs")``.
        """

        pixels: NestedKey = "pixels"
        action: NestedKey = "action"
        next_pixels: NestedKey = ("next", "pixels")
        code: NestedKey = "code"
        next_code: NestedKey = ("next", "code")
        code_probs: NestedKey = "code_probs"
        next_code_probs: NestedKey = ("next", "code_probs")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        model: LatentWorldModel,
        code_encoder: nn.Module,
        *,
        open_loop_length: int | None = None,
        pixel_weight: float = 1.0,
        latent_weight: float = 0.1,
        soft_targets: bool = False,
        hard_weight: float = 0.0,
        change_weight: float = 0.0,
        pixel_steps: int | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(model, LatentWorldModel):
            raise ValueError(f"model must be a LatentWorldModel, got {type(model).__name__}.")
        frame_shape = getattr(code_encoder, "frame_shape", model.frame_shape)
        check_latent_model(model, getattr(code_encoder, "code_sizes", ()), frame_shape)
        self.model = model
        self.code_encoder = code_encoder
        self.code_encoder.requires_grad_(False)
        self.open_loop_length = check_int(
            "open_loop_length", open_loop_length, low=1, optional=True
        )
        self.pixel_weight = check_float("pixel_weight", pixel_weight, low=0.0)
        self.latent_weight = check_float("latent_weight", latent_weight, low=0.0)
        self.soft_targets = check_bool("soft_targets", soft_targets)
        self.hard_weight = check_float("hard_weight", hard_weight, low=0.0)
        self.change_weight = check_float("change_weight", change_weight, low=0.0)
        self.pixel_steps = check_int("pixel_steps", pixel_steps, low=1, optional=True)

    def _read(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames ``[B, H + 1, C, H', W']`` (o_t .. o_{t+H}) and actions ``[B, H]``."""
        keys = self.tensor_keys
        values = {}
        for name in ("pixels", "action", "next_pixels"):
            key = getattr(keys, name)
            value = td.get(key, None)
            if value is None:
                raise MissingKeyError(
                    f"LatentWorldModelLoss needs {key!r} ([B, H, ...] windows, e.g. a "
                    "SequenceSampler sample)."
                )
            values[name] = value
        pixels, nxt = values["pixels"], values["next_pixels"]
        frames = torch.cat([pixels[:, :1], nxt], 1)
        action = values["action"].reshape(*pixels.shape[:2], -1)[..., 0].long()
        n = self.model.num_actions
        if bool(((action < 0) | (action >= n)).any()):
            raise ValueError(
                f"the windows hold actions outside [0, {n}); the model takes actions in "
                f"[0, {n}) (int indices [B, H, 1]; one-hot actions are turned into indices "
                "by the trainer)."
            )
        return frames, action

    @torch.no_grad()
    def encode_targets(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The code encoder's codes ``[N, K]`` and probabilities ``[N, K, Z]`` of the
        frames ``[*B, C, H, W]`` flattened, in eval mode (its mode restored after)."""
        encoder = self.code_encoder
        with eval_mode(encoder):
            flat = frames.reshape(-1, *frames.shape[-3:]).to(module_device(encoder))
            code, probs = encoder(flat)
        return code.to(frames.device), probs.to(frames.device)

    def target_codes(self, frames: torch.Tensor) -> torch.Tensor:
        """The code encoder's codes int64 ``[*B, K]`` of frames ``[*B, C, H, W]``."""
        code = self.encode_targets(frames)[0]
        return code.to(torch.int64).reshape(*frames.shape[:-3], -1)

    def target_probs(self, frames: torch.Tensor) -> list[torch.Tensor]:
        """The code encoder's code probabilities of frames ``[*B, C, H, W]``: one
        ``[*B, code_sizes[k]]`` per one-hot."""
        probs = self.encode_targets(frames)[1]
        return self._per_onehot(probs.reshape(*frames.shape[:-3], *probs.shape[-2:]))

    def _per_onehot(self, probs: torch.Tensor) -> list[torch.Tensor]:
        """``[*B, K, Z]`` probabilities as one ``[*B, code_sizes[k]]`` per one-hot."""
        return [probs[..., k, :size] for k, size in enumerate(self.model.code_sizes)]

    def given_probs(self, td: TensorDictBase) -> list[torch.Tensor] | None:
        """The windows' code probabilities (one ``[B, H + 1, code_sizes[k]]`` per
        one-hot) from ``code_probs`` and ``("next", "code_probs")``, or ``None`` when the
        tensordict lacks them."""
        probs = td.get(self.tensor_keys.code_probs, None)
        nxt = td.get(self.tensor_keys.next_code_probs, None)
        if probs is None or nxt is None:
            return None
        return self._per_onehot(torch.cat([probs[:, :1], nxt], 1).float())

    def given_codes(self, td: TensorDictBase) -> torch.Tensor | None:
        """The windows' codes ``[B, H + 1, K]`` from ``code`` and ``("next", "code")``, or
        ``None`` when the tensordict lacks them."""
        code = td.get(self.tensor_keys.code, None)
        nxt = td.get(self.tensor_keys.next_code, None)
        if code is None or nxt is None:
            return None
        return torch.cat([code[:, :1], nxt], 1).long()

    def rollout(
        self, frames: torch.Tensor, action: torch.Tensor, *, logits: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Latents ``[B, H + 1, D]``: the encoded o_t, then one per action, restarted from
        the encoded true frame every ``open_loop_length`` steps; with ``logits``, also the
        dynamics' outputs ``[B, H, D]`` (:meth:`~dorp_rl.modules.LatentWorldModel.step_logits`)."""
        model = self.model
        every = self.open_loop_length or action.shape[1]
        latent = model.encode(frames[:, 0])
        out, raw = [latent], []
        for t in range(action.shape[1]):
            if t > 0 and t % every == 0:
                latent = model.encode(frames[:, t])
            step = model.step_logits(latent, action[:, t])
            latent = model.quantize(step) if model.discrete else model.dynamics_norm(step)
            out.append(latent)
            raw.append(step)
        latents = torch.stack(out, 1)
        return (latents, torch.stack(raw, 1)) if logits else latents

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        frames, action = self._read(tensordict)
        model = self.model
        latents, raw = self.rollout(frames, action, logits=True)
        targets = self.given_codes(tensordict)
        if targets is None:
            targets = self.target_codes(frames)  # [B, H + 1, K]
        logits = model.code_logits(latents).split(model.code_sizes, dim=-1)
        if self.soft_targets:
            probs = self.given_probs(tensordict)
            if probs is None:
                probs = self.target_probs(frames)
            loss_code = sum(
                -(target * F.log_softmax(part, -1)).sum(-1).mean()
                for part, target in zip(logits, probs, strict=True)
            )
        hard_weight = 1.0 if not self.soft_targets else self.hard_weight
        if hard_weight > 0:
            hard = sum(
                F.cross_entropy(part.reshape(-1, part.shape[-1]), targets[..., k].reshape(-1))
                for k, part in enumerate(logits)
            )
            loss_code = hard_weight * hard + (loss_code if self.soft_targets else 0.0)
        predicted = torch.stack([part.argmax(-1) for part in logits], -1)
        right = (predicted == targets).all(-1)[:, 1:].float()
        with torch.no_grad():
            encoded = model.encode_logits(frames[:, 1:])
        if model.discrete:
            # Each imagined categorical variable against the one the true frame gets.
            truth = model.latent_classes(encoded)
            step = raw.reshape(*truth.shape, -1)
            loss_latent = F.cross_entropy(step.reshape(-1, step.shape[-1]), truth.reshape(-1))
        else:
            loss_latent = F.mse_loss(latents[:, 1:], model.encoder_norm(encoded))
        loss_latent = self.latent_weight * loss_latent
        out = {
            "loss_code": loss_code,
            "loss_latent": loss_latent,
            "code_accuracy": right.mean().detach(),
            "code_accuracy_last": right[:, -1].mean().detach(),
        }
        if model.frame_decoder is not None:
            out.update(self._pixel_terms(latents, frames_to_unit_float(frames)))
        return TensorDict(out, batch_size=[])

    def _pixel_terms(self, latents: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
        """``loss_pixels``, ``loss_change`` and ``pixel_error`` of the decoded latents
        ``[B, H + 1, D]`` against the true frames ``[B, H + 1, C, H', W']`` in [0, 1], on
        ``pixel_steps`` random steps of each window (all steps if None)."""
        # Each step's frame before it (o_t's own for step 0, so nothing changed there),
        # only for the change term.
        before = torch.cat([truth[:, :1], truth[:, :-1]], 1) if self.change_weight > 0 else None
        steps = truth.shape[1]
        if self.pixel_steps is not None and self.pixel_steps < steps:
            order = torch.rand(truth.shape[:2], device=truth.device).argsort(-1)
            index = order[:, : self.pixel_steps]  # [B, n]

            def pick(x: torch.Tensor) -> torch.Tensor:
                shaped = index.reshape(*index.shape, *(1,) * (x.dim() - 2))
                return x.gather(1, shaped.expand(*index.shape, *x.shape[2:]))

            latents, truth = pick(latents), pick(truth)
            before = None if before is None else pick(before)
        decoded = self.model.decode(latents)
        out = {"loss_pixels": self.pixel_weight * F.mse_loss(decoded, truth)}
        if before is not None:
            changed = (truth != before).to(truth.dtype)
            error = (decoded - truth).square() * changed
            out["loss_change"] = self.change_weight * error.sum() / changed.sum().clamp(min=1)
        out["pixel_error"] = (decoded - truth).abs().mean().detach()
        return out
