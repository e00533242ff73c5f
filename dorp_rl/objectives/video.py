"""VideoPredictionLoss: per-pixel palette cross-entropy over open-loop rollouts, plus KL."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from dorp_rl.frames import check_frames
from dorp_rl.modules.video import VideoPredictionModel
from dorp_rl.validation import MissingKeyError, check_choice, check_float, check_int

FEEDBACK_MODES = ("straight_through", "soft", "hard")


def gaussian_kl(
    mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor, std_p: torch.Tensor
) -> torch.Tensor:
    """Elementwise ``KL(N(mean_q, std_q^2) || N(mean_p, std_p^2))`` of diagonal Gaussians."""
    var_ratio = (std_q / std_p) ** 2
    return 0.5 * (var_ratio + ((mean_q - mean_p) / std_p) ** 2 - 1.0 - var_ratio.log())


class VideoPredictionLoss(LossModule):
    """Trains a :class:`~dorp_rl.modules.VideoPredictionModel` on ``[B, H]`` windows.

    The model rolls out over the window from the first frame o_t, feeding on its own
    predictions, and every predicted frame is scored by a per-pixel cross-entropy
    against the palette index of the true frame. The rollout restarts from the true
    frame every ``open_loop_length`` steps: 1 is pure teacher forcing (one-step
    prediction), ``H`` (or ``None``) a single open-loop rollout over the whole window. A
    trainer grows it during training (the measured recipe: open-loop rollouts of growing
    length keep long rollouts sharp). Own predictions are fed back as:

    - ``"straight_through"`` (default): the hard one-hot of the argmax in the forward
      pass (what the model sees at test time), the softmax's gradient in the backward;
    - ``"soft"``: the softmax itself (the soft palette expectation);
    - ``"hard"``: the hard one-hot, no gradient through the feedback.

    Latent: at every step ``z`` is drawn from the posterior ``q(z | o_t, o_{t+1}, a_t)``
    of the *true* frames; ``loss_kl = kl_weight * sum_d max(KL_d, free_bits)`` with
    ``KL_d`` the batch- and step-averaged KL to the prior of latent dimension ``d``.
    A ``deterministic_fraction`` of the window rows uses the prior mean instead of a
    posterior draw: the deterministic mode (used for planning) is then trained directly
    and cannot lean on information the posterior smuggles from the future (SV2P trains a
    deterministic phase first for the same reason).

    Reads ``pixels`` ``[B, H, 3, 16, 16]`` (only o_t = ``pixels[:, 0]`` and the
    restarts use it), ``action`` ``[B, H, 1]`` and ``("next", "pixels")``
    ``[B, H, 3, 16, 16]``, e.g. a :class:`~dorp_rl.data.SequenceSampler` sample.

    Returns ``loss_reconstruction`` (mean cross-entropy per pixel), ``loss_kl`` (0 for a
    model without latent) and detached metrics: ``pixel_accuracy`` and
    ``frame_accuracy`` (share of predicted frames with every pixel right, over the
    window), ``last_frame_accuracy`` (last step of the window), ``kl`` (unweighted,
    summed over latent dimensions) and ``open_loop_length``.

    Args:
        model: the video model.
        open_loop_length: steps between restarts from the true frame (``None``: whole window).
        feedback: ``"straight_through"``, ``"soft"`` or ``"hard"`` (see above).
        kl_weight: weight of the KL term.
        free_bits: nats per latent dimension not penalised.
        deterministic_fraction: share of rows trained with the prior mean as ``z``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
        >>> from dorp_rl.objectives.video import VideoPredictionLoss
        >>> palette = torch.tensor([[0, 0, 0], [255, 255, 0]], dtype=torch.uint8)
        >>> model = VideoPredictionModel(4, palette, VideoModelConfig.small())
        >>> frames = torch.zeros(2, 3, 3, 16, 16, dtype=torch.uint8)
        >>> td = TensorDict(pixels=frames, action=torch.zeros(2, 3, 1, dtype=torch.int64),
        ...                 next=TensorDict(pixels=frames, batch_size=[2, 3]), batch_size=[2, 3])
        >>> out = VideoPredictionLoss(model)(td)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_kl', 'loss_reconstruction']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads.

        Attributes:
            pixels: frames o_t .. o_{t+H-1}, uint8 ``[B, H, 3, 16, 16]``. Defaults to ``"pixels"``.
            action: actions a_t .. a_{t+H-1}, int64 ``[B, H, 1]``. Defaults to ``"action"``.
            next_pixels: frames o_{t+1} .. o_{t+H}. Defaults to ``("next", "pixels")``.
        """

        pixels: NestedKey = "pixels"
        action: NestedKey = "action"
        next_pixels: NestedKey = ("next", "pixels")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        model: VideoPredictionModel,
        *,
        open_loop_length: int | None = None,
        feedback: str = "straight_through",
        kl_weight: float = 1.0,
        free_bits: float = 0.0,
        deterministic_fraction: float = 0.5,
    ) -> None:
        super().__init__()
        if not isinstance(model, VideoPredictionModel):
            raise ValueError(f"model must be a VideoPredictionModel, got {type(model).__name__}.")
        self.model = model
        self.open_loop_length = open_loop_length
        self.feedback = check_choice("feedback", feedback, FEEDBACK_MODES)
        self.kl_weight = check_float("kl_weight", kl_weight, low=0.0)
        self.free_bits = check_float("free_bits", free_bits, low=0.0)
        self.deterministic_fraction = check_float(
            "deterministic_fraction", deterministic_fraction, low=0.0, high=1.0
        )

    @property
    def open_loop_length(self) -> int | None:
        """Steps between restarts from the true frame (``None``: the whole window)."""
        return self._open_loop_length

    @open_loop_length.setter
    def open_loop_length(self, value: int | None) -> None:
        self._open_loop_length = check_int("open_loop_length", value, low=1, optional=True)

    def _read(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        keys = self.tensor_keys
        values = []
        for name in ("pixels", "action", "next_pixels"):
            key = getattr(keys, name)
            value = tensordict.get(key, None)
            if value is None:
                raise MissingKeyError(f"VideoPredictionLoss needs the key {key!r} ({name}).")
            values.append(value)
        pixels, action, next_pixels = values
        for name, value in (("pixels", pixels), ("next_pixels", next_pixels)):
            check_frames(
                value, f"{name} (a window sample)", lead="B, H", shape=self.model.frame_shape
            )
        if pixels.shape != next_pixels.shape:
            raise ValueError(
                f"pixels and next_pixels must have the same shape, got {list(pixels.shape)} "
                f"and {list(next_pixels.shape)}."
            )
        b, h = pixels.shape[:2]
        self.model._check_action(action, (b, h, 1))
        return pixels, action, next_pixels

    def _feed(self, logits: torch.Tensor) -> torch.Tensor:
        if self.feedback == "soft":
            return logits.softmax(1)
        hard = F.one_hot(logits.argmax(1), logits.shape[1]).movedim(-1, 1).to(logits.dtype)
        if self.feedback == "hard":
            return hard
        soft = logits.softmax(1)
        return hard + soft - soft.detach()

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        pixels, action, next_pixels = self._read(tensordict)
        model = self.model
        b, horizon = pixels.shape[:2]
        # True frames o_t .. o_{t+H} as palette indices and one-hots.
        frames = torch.cat([pixels[:, :1], next_pixels], dim=1)
        index = model.palette_index(frames)  # [B, H+1, 16, 16]
        true_probs = F.one_hot(index, model.num_colours).movedim(-1, 2).float()
        restart = self.open_loop_length or horizon
        use_latent = model.latent_dim > 0
        if use_latent:
            det_rows = torch.rand(b, device=pixels.device) < self.deterministic_fraction
        ce_total = pixels.new_zeros((), dtype=torch.float32)
        kl_dims = None
        correct_pixels = 0.0
        correct_frames = 0.0
        last_correct = pixels.new_zeros(())
        x = true_probs[:, 0]
        for h in range(horizon):
            if h % restart == 0:
                x = true_probs[:, h]
            a = action[:, h]
            z = None
            if use_latent:
                mean_q, std_q = model.posterior(true_probs[:, h], true_probs[:, h + 1], a)
                mean_p, std_p = model.prior(x, a)
                z = mean_q + std_q * torch.randn_like(mean_q)
                z = torch.where(det_rows.unsqueeze(-1), mean_p, z)
                kl = gaussian_kl(mean_q, std_q, mean_p, std_p).mean(0)  # [D]
                kl_dims = kl if kl_dims is None else kl_dims + kl
            logits = model.step_logits(x, a, z)
            target = index[:, h + 1]
            ce_total = ce_total + F.cross_entropy(logits, target)
            with torch.no_grad():
                right = logits.argmax(1) == target  # [B, 16, 16]
                correct_pixels += float(right.float().mean())
                whole = right.flatten(1).all(-1).float().mean()
                correct_frames += float(whole)
                last_correct = whole
            x = self._feed(logits)
        loss_rec = ce_total / horizon
        if kl_dims is not None:
            kl_dims = kl_dims / horizon
            kl_sum = kl_dims.sum()
            loss_kl = self.kl_weight * kl_dims.clamp_min(self.free_bits).sum()
        else:
            kl_sum = loss_rec.new_zeros(())
            loss_kl = loss_rec.new_zeros(())
        return TensorDict(
            loss_reconstruction=loss_rec,
            loss_kl=loss_kl,
            pixel_accuracy=torch.tensor(correct_pixels / horizon),
            frame_accuracy=torch.tensor(correct_frames / horizon),
            last_frame_accuracy=last_correct.detach().float(),
            kl=kl_sum.detach(),
            open_loop_length=torch.tensor(float(min(restart, horizon))),
            batch_size=[],
        )
