"""Stochastic action-conditioned video prediction for 16x16 palette frames (SV2P-style).

The frames of the paper's environments use a handful of flat colours (a black
background and one colour per object, wall, door, ...). :class:`VideoPredictionModel`
therefore predicts, for every pixel, scores over that *palette* instead of RGB values:
predicted frames are always made of palette colours, never blur and never drift in
colour, and training is a per-pixel cross-entropy.

Layout of one prediction step (accuracy and speed in ``docs/RESULTS.md``):

1. the frame's palette one-hot ``[N, K, 16, 16]`` is folded (space-to-depth) to an 8x8
   grid of ``4 K`` channels, the action one-hot and the latent ``z`` are broadcast as
   extra input channels;
2. a 3x3 stem conv and residual blocks of dilated 3x3 convs; every block is modulated
   (FiLM) by the action and ``z`` and by a global max-pool of its own features, so that
   a fact seen anywhere (e.g. "the block to move touches an obstacle on that side")
   reaches every cell in one block;
3. a 1x1 conv gives ``4 K`` scores per cell, unfolded to ``[N, K, 16, 16]``, plus an
   advection path in the spirit of SV2P's CDNA: from the pooled trunk features, one
   softmax 3x3 kernel per palette colour moves that colour's map by at most one pixel;
   the background (the first palette colour, black in every dorp-rl env) is what the
   moved colours leave free. The kernel head also reads, per colour and shift, how
   much the colour would overlap other colours or leave the frame (blocked moves are
   the hard case of these worlds). A learned gain times this advected frame is added to the
   scores, so "each object moves as a whole, or not at all" is the easy default and
   "nothing changes" is where training starts (the kernels start near the identity);
4. frames come back by palette lookup of the per-pixel argmax.

The latent variable follows SV2P: at training time ``z`` is drawn from a posterior
``q(z | o_t, o_{t+1}, a_t)`` that sees the future frame, at test time from a prior,
``N(0, I)`` (``prior="fixed"``) or a learned ``p(z | o_t, a_t)`` (``prior="learned"``).
The deterministic mode uses the prior mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from torch import nn

from dorp_rl.config import Choice, ConfigMixin, Flag, Float, Int, Ints, checked
from dorp_rl.frames import frames_to_uint8
from dorp_rl.validation import check_action, check_int

FRAME_SHAPE = (3, 16, 16)


# --------------------------------------------------------------------------- palette
def _pack_rgb(colours: torch.Tensor) -> torch.Tensor:
    """uint8 ``[..., 3]`` (channel last) -> int32 ``[...]`` codes ``r << 16 | g << 8 | b``."""
    c = colours.to(torch.int32)
    return (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]


def palette_from_frames(frames: torch.Tensor, max_colours: int = 64) -> torch.Tensor:
    """The distinct colours of uint8 frames ``[*B, 3, H, W]`` as a uint8 palette ``[K, 3]``.

    Black (the background of every dorp-rl env), if present, comes first; the other
    colours follow in increasing ``(r, g, b)`` order, so the same data always give the
    same palette.

    Args:
        frames: uint8 images, channel first (e.g. all ``pixels`` of a play buffer).
        max_colours: refuse more colours than this (natural images are not palette frames).

    Raises:
        ValueError: frames of another dtype or layout, or more than ``max_colours`` colours.

    Examples:
        >>> import torch
        >>> frames = torch.zeros(2, 3, 16, 16, dtype=torch.uint8)
        >>> frames[0, 0, :2, :4] = 255  # a red block
        >>> palette_from_frames(frames).tolist()
        [[0, 0, 0], [255, 0, 0]]
    """
    frames = frames_to_uint8(frames, "frames")
    codes = _pack_rgb(frames.movedim(-3, -1).reshape(-1, 3)).unique()
    if codes.numel() > max_colours:
        raise ValueError(
            f"frames hold {codes.numel()} distinct colours, more than max_colours={max_colours}: "
            "a palette model needs flat-coloured frames."
        )
    codes = codes.sort().values  # black (code 0) first if present
    rgb = torch.stack([(codes >> 16) & 255, (codes >> 8) & 255, codes & 255], dim=-1)
    return rgb.to(torch.uint8)


def check_palette(palette: torch.Tensor) -> torch.Tensor:
    """Validates a palette: uint8 ``[K, 3]`` with ``K >= 2`` distinct colours."""
    if not isinstance(palette, torch.Tensor):
        palette = torch.as_tensor(palette)
    if palette.dtype != torch.uint8:
        if palette.dtype.is_floating_point or palette.min() < 0 or palette.max() > 255:
            raise ValueError(f"palette must be uint8 [K, 3] colours (0-255), got {palette.dtype}.")
        palette = palette.to(torch.uint8)
    if palette.dim() != 2 or palette.shape[1] != 3 or palette.shape[0] < 2:
        raise ValueError(f"palette must have shape [K, 3] with K >= 2, got {list(palette.shape)}.")
    if _pack_rgb(palette).unique().numel() != palette.shape[0]:
        raise ValueError("palette colours must be distinct.")
    return palette


# --------------------------------------------------------------------------- config
@dataclass
class VideoModelConfig(ConfigMixin):
    """Sizes of :class:`VideoPredictionModel`.

    Use :meth:`small` (fast, for planning with thousands of candidates) or
    :meth:`default` (more accurate), then override fields.

    Examples:
        >>> from dorp_rl.modules import VideoModelConfig
        >>> cfg = VideoModelConfig.small(latent_dim=0)  # a deterministic model
        >>> cfg.channels, cfg.dilations, cfg.latent_dim
        (16, (1, 2, 4), 0)
    """

    channels: int = checked(32, Int(low=1))
    """width of the residual trunk (on the 8x8 grid)"""
    dilations: tuple[int, ...] = checked((1, 2, 4, 1), Ints(low=1))
    """one residual block per entry: its 3x3 conv's dilation ((1, 2, 4, 1) sees 9 cells)"""
    global_context: bool = checked(True, Flag())
    """add a global max-pool of each block's features to its FiLM"""
    latent_dim: int = checked(4, Int(low=0))
    """size of the latent z (0: a deterministic model)"""
    prior: str = checked("fixed", Choice(("fixed", "learned")))
    """prior of z: fixed (N(0, I)) or learned (p(z | o_t, a_t))"""
    latent_channels: int = checked(16, Int(low=1))
    """width of the posterior / prior conv nets"""
    copy_init: float = checked(4.0, Float())
    """initial gain of the advection path (score added to the advected input colours)"""
    advection: bool = checked(True, Flag())
    """move each colour's map by a predicted 3x3 kernel before the copy path (off: copy)"""
    collision_features: bool = checked(True, Flag())
    """tell the kernel head how much each colour would overlap others or leave, per shift"""

    @classmethod
    def small(cls, **overrides: Any) -> VideoModelConfig:
        """About 15k parameters: 16 channels, dilations 1, 2, 4."""
        return cls(**{"channels": 16, "dilations": (1, 2, 4), **overrides})

    @classmethod
    def default(cls, **overrides: Any) -> VideoModelConfig:
        """About 60k parameters: 32 channels, dilations 1, 2, 4, 1."""
        return cls(**overrides)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> VideoModelConfig:
        """``"small"`` or ``"default"``."""
        if name not in ("small", "default"):
            raise ValueError(f"video model preset must be 'small' or 'default', got {name!r}.")
        return getattr(cls, name)(**overrides)


# --------------------------------------------------------------------------- blocks
class _ResidualBlock(nn.Module):
    """Pre-activation dilated 3x3 conv, FiLM from (action, z) and global context, 1x1 mix."""

    def __init__(self, channels: int, dilation: int, cond_dim: int, global_context: bool) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=dilation, dilation=dilation)
        self.film = nn.Linear(cond_dim, 2 * channels)
        self.context = nn.Linear(channels, 2 * channels) if global_context else None
        self.mix = nn.Conv2d(channels, channels, 1)

    def forward(self, h: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        u = self.conv(F.relu(h))
        gamma, beta = self.film(cond)[..., :, None, None].chunk(2, dim=1)
        u = F.relu(torch.addcmul(beta, u, 1.0 + gamma))
        v = self.mix(u)
        if self.context is not None:
            # What the action-modulated features saw anywhere on the grid gates the update.
            gamma, beta = self.context(u.amax(dim=(-2, -1)))[..., :, None, None].chunk(2, dim=1)
            return torch.addcmul(h + beta, v, 1.0 + gamma)
        return h + v


class _GaussianNet(nn.Module):
    """Small conv net from grid features to a diagonal Gaussian ``(mean, std)`` over ``z``."""

    def __init__(self, in_channels: int, width: int, latent_dim: int) -> None:
        super().__init__()
        self.convs = nn.Sequential(
            nn.Conv2d(in_channels, width, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2),
            nn.ReLU(),
        )
        self.head = nn.Linear(2 * width, 2 * latent_dim)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.convs(x)
        pooled = torch.cat([h.mean(dim=(-2, -1)), h.amax(dim=(-2, -1))], dim=-1)
        mean, raw_std = self.head(pooled).chunk(2, dim=-1)
        return mean, F.softplus(raw_std + 0.5413) + 1e-4  # softplus(0.5413) = 1


# --------------------------------------------------------------------------- model
class VideoPredictionModel(nn.Module):
    """Stochastic action-conditioned next-frame prediction over a colour palette.

    Args:
        num_actions: size of the discrete action space (actions are int64 ``[N, 1]``).
        palette: uint8 ``[K, 3]``, every colour the frames use (background included),
            e.g. from :func:`palette_from_frames` on play data. Input pixels of another
            colour are read as the nearest palette colour.
        config: sizes (:class:`VideoModelConfig`; default :meth:`VideoModelConfig.default`).

    Shapes (``N`` frames, ``K`` palette colours, ``D = config.latent_dim``):

    - :meth:`logits` / ``forward``: pixels uint8 ``[N, 3, 16, 16]``, action int64
      ``[N, 1]``, optional ``z`` ``[N, D]`` -> per-pixel palette logits ``[N, K, 16, 16]``;
    - :meth:`predict`: -> next frame uint8 ``[N, 3, 16, 16]`` (palette colours only);
    - :meth:`rollout`: actions ``[N, H, 1]`` -> open-loop frames uint8 ``[N, H, 3, 16, 16]``.

    Training goes through :class:`~dorp_rl.objectives.VideoPredictionLoss`, which works
    on palette probabilities (:meth:`frame_probs`, :meth:`step_logits`, :meth:`posterior`,
    :meth:`prior`).

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
        >>> env = ObjectRearrangementEnv(2, batch_size=(), batch_locked=False, seed=0)
        >>> palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours])
        >>> model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small())
        >>> pixels = env.render_state(env.sample_states((5,)))
        >>> action = torch.randint(env.num_actions, (5, 1))
        >>> model.logits(pixels, action).shape
        torch.Size([5, 3, 16, 16])
        >>> model.predict(pixels, action).dtype, model.rollout(pixels, action.expand(5, 4).unsqueeze(-1)).shape
        (torch.uint8, torch.Size([5, 4, 3, 16, 16]))
    """

    frame_shape: tuple[int, int, int] = FRAME_SHAPE
    """The frames this model reads and predicts, ``(C, H, W)``."""

    def __init__(
        self,
        num_actions: int,
        palette: torch.Tensor,
        config: VideoModelConfig | None = None,
    ) -> None:
        super().__init__()
        config = VideoModelConfig.default() if config is None else config
        config.validate()
        num_actions = check_int("num_actions", num_actions, low=1)
        palette = check_palette(palette)
        self.config = config
        self.num_actions = int(num_actions)
        self.num_colours = int(palette.shape[0])
        self.latent_dim = int(config.latent_dim)
        self.register_buffer("palette", palette.clone())
        self.register_buffer("_palette_codes", _pack_rgb(palette), persistent=False)
        # [3, K, 1, 1] weights of the 1x1 conv that draws a one-hot frame in RGB.
        self.register_buffer(
            "_palette_weight", palette.float().t().reshape(3, -1, 1, 1), persistent=False
        )
        k, c, a, d = self.num_colours, config.channels, self.num_actions, self.latent_dim
        grid = 4 * k
        self.stem = nn.Conv2d(grid + a + d, c, 3, padding=1)
        self.blocks = nn.ModuleList(
            _ResidualBlock(c, int(dil), a + d, config.global_context) for dil in config.dilations
        )
        self.head = nn.Conv2d(c, grid, 1)
        self.copy_gain = nn.Parameter(torch.tensor(float(config.copy_init)))
        if config.advection:
            collision = 2 * k * 9 if config.collision_features else 0
            self.kernel_head = nn.Linear(2 * c + a + d + collision, k * 9)
            nn.init.zeros_(self.kernel_head.weight)
            # Centre tap ~0.5 at the start: the argmax frame is still a copy, yet every
            # tap gets gradient (from a saturated softmax the kernels never learn to move).
            with torch.no_grad():
                self.kernel_head.bias.copy_(
                    torch.zeros(k, 9).index_fill_(1, torch.tensor([4]), 2.0).flatten()
                )
        else:
            self.kernel_head = None
        self.posterior_net = _GaussianNet(2 * grid + a, config.latent_channels, d) if d else None
        self.prior_net = (
            _GaussianNet(grid + a, config.latent_channels, d)
            if d and config.prior == "learned"
            else None
        )

    # ------------------------------------------------------------------ checks
    def _check_pixels(self, pixels: torch.Tensor, name: str = "pixels") -> torch.Tensor:
        """Frames ``[N, 3, 16, 16]`` as uint8: uint8 ones as they are, floats in ``[0, 1]``
        (any precision) scaled by 255 and rounded (palette colours are exact bytes)."""
        return frames_to_uint8(pixels, name, lead="N", shape=FRAME_SHAPE)

    def _check_action(
        self, action: torch.Tensor, shape: tuple[int, ...], name: str = "action"
    ) -> torch.Tensor:
        return check_action(action, self.num_actions, name, shape=shape)

    def _check_z(self, z: torch.Tensor, n: int) -> None:
        if not isinstance(z, torch.Tensor) or tuple(z.shape) != (n, self.latent_dim):
            got = list(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
            raise ValueError(f"z must be a float tensor [{n}, {self.latent_dim}], got {got}.")

    # ------------------------------------------------------------------ palette
    def palette_index(self, pixels: torch.Tensor) -> torch.Tensor:
        """Palette index of every pixel: uint8 ``[*B, 3, 16, 16]`` -> int64 ``[*B, 16, 16]``.

        Colours outside the palette map to the nearest palette colour (L1 in RGB).
        """
        codes = _pack_rgb(pixels.movedim(-3, -1))  # [*B, 16, 16]
        match = codes.unsqueeze(-1) == self._palette_codes  # [*B, 16, 16, K]
        index = match.to(torch.uint8).argmax(-1)
        if not bool(match.any(-1).all()):
            diff = pixels.movedim(-3, -1).unsqueeze(-2).float() - self.palette.float()
            index = diff.abs().sum(-1).argmin(-1)
        return index

    def frame_probs(self, pixels: torch.Tensor) -> torch.Tensor:
        """Palette one-hot of frames: uint8 ``[*B, 3, 16, 16]`` -> float ``[*B, K, 16, 16]``."""
        index = self.palette_index(pixels)
        return F.one_hot(index, self.num_colours).movedim(-1, -3).float()

    def frames_from_index(self, index: torch.Tensor) -> torch.Tensor:
        """Palette lookup: int64 ``[*B, 16, 16]`` -> uint8 ``[*B, 3, 16, 16]``."""
        return self.palette[index].movedim(-1, -3).contiguous()

    def frames_from_logits(self, logits: torch.Tensor) -> torch.Tensor:
        """Most likely colour per pixel: ``[N, K, 16, 16]`` -> uint8 ``[N, 3, 16, 16]``.

        A max-mask drawn by a 1x1 conv with the palette as weights (faster than an index
        lookup on CPU); ties, which trained models do not produce, take the lowest index.
        """
        mask = logits == logits.amax(dim=1, keepdim=True)
        if bool((mask.sum(1) > 1).any()):
            return self.frames_from_index(logits.argmax(1))
        frame = F.conv2d(mask.to(logits.dtype), self._palette_weight)
        return frame.round_().to(torch.uint8)

    # ------------------------------------------------------------------ core
    def _action_onehot(self, action: torch.Tensor) -> torch.Tensor:
        return F.one_hot(action.reshape(-1), self.num_actions).to(self.stem.weight.dtype)

    def _grid(self, probs: torch.Tensor) -> torch.Tensor:
        return F.pixel_unshuffle(probs, 2)  # [N, 4K, 8, 8]

    def step_logits(
        self, probs: torch.Tensor, action: torch.Tensor, z: torch.Tensor | None = None
    ) -> torch.Tensor:
        """One prediction step on palette probabilities (differentiable in ``probs``).

        Args:
            probs: float ``[N, K, 16, 16]``, a one-hot frame or soft palette probabilities.
            action: int64 ``[N, 1]`` (not checked here).
            z: float ``[N, D]`` latent; ``None`` uses the prior mean.

        Returns:
            next-frame palette logits ``[N, K, 16, 16]``.
        """
        n = probs.shape[0]
        a = self._action_onehot(action)
        if self.latent_dim:
            if z is None:
                z = self.prior(probs, action)[0]
            cond = torch.cat([a, z], dim=-1)
        else:
            cond = a
        grid = self._grid(probs)
        x = torch.cat([grid, cond[:, :, None, None].expand(n, cond.shape[1], 8, 8)], dim=1)
        h = self.stem(x)
        for block in self.blocks:
            h = block(h, cond)
        out = F.pixel_shuffle(self.head(F.relu(h)), 2)
        if self.kernel_head is not None:
            probs = self._advect(probs, h, cond)
        return out + self.copy_gain * probs

    def _advect(self, probs: torch.Tensor, h: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """Moves each colour map by its own predicted 3x3 kernel: ``[N, K, 16, 16]`` -> same.

        Kernel tap ``(i, j)`` takes the value from ``(row + 1 - i, column + 1 - j)``'s
        neighbour, i.e. moves the map by ``(i - 1, j - 1)``. The background channel is
        recomputed as what the other colours leave uncovered.
        """
        n, k = probs.shape[:2]
        features = [F.relu(h.mean(dim=(-2, -1))), F.relu(h.amax(dim=(-2, -1))), cond]
        if self.config.collision_features:
            features.append(self._collisions(probs))
        kernels = self.kernel_head(torch.cat(features, dim=-1)).view(n, k, 9).softmax(-1)
        # One depthwise conv over all N * K maps; conv2d correlates, so tap (i, j) of the
        # flipped kernel reads the neighbour at (1 - i, 1 - j).
        weight = kernels.view(n * k, 1, 3, 3).flip(-2, -1)
        moved = F.conv2d(probs.reshape(1, n * k, 16, 16), weight, padding=1, groups=n * k)
        moved = moved.view(n, k, 16, 16)
        background = (1.0 - moved[:, 1:].sum(1, keepdim=True)).clamp(0.0, 1.0)
        return torch.cat([background, moved[:, 1:]], dim=1)

    @staticmethod
    def _collisions(probs: torch.Tensor) -> torch.Tensor:
        """What each colour would run into if moved by each of the 9 shifts: ``[N, 2 * K * 9]``.

        For colour ``c`` and shift ``t`` (kernel tap order): the share of ``c``'s mass that
        would land on another non-background colour, and the share that would leave the
        frame. Zero for a free move; the kernel head reads them linearly, so "objects do
        not pass through each other or the border" is one weight away.
        """
        n, k = probs.shape[:2]
        total = probs.sum(dim=(-2, -1))  # [N, K]
        mass = total.clamp(min=1.0)
        others = (1.0 - probs[:, :1] - probs).clamp(min=0.0)  # [N, K, 16, 16]
        padded = F.pad(probs, (1, 1, 1, 1))
        overlap, lost = [], []
        for i in range(3):
            for j in range(3):
                shifted = padded[:, :, 2 - i : 18 - i, 2 - j : 18 - j]
                overlap.append((shifted * others).sum(dim=(-2, -1)))
                lost.append(total - shifted.sum(dim=(-2, -1)))
        out = torch.stack(overlap + lost, dim=-1) / mass[..., None]  # [N, K, 18]
        return out.reshape(n, -1)

    def prior(self, probs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Prior ``(mean, std)`` of ``z``, each ``[N, D]``: ``N(0, I)`` or ``p(z | o_t, a_t)``."""
        n = probs.shape[0]
        if self.prior_net is None:
            zeros = probs.new_zeros(n, self.latent_dim)
            return zeros, torch.ones_like(zeros)
        a = self._action_onehot(action)
        x = torch.cat([self._grid(probs), a[:, :, None, None].expand(n, -1, 8, 8)], dim=1)
        return self.prior_net(x)

    def posterior(
        self, probs: torch.Tensor, next_probs: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior ``(mean, std)`` of ``z``, each ``[N, D]``, from o_t, o_{t+1} and a_t."""
        if self.posterior_net is None:
            raise RuntimeError("this model has no latent variable (latent_dim=0).")
        n = probs.shape[0]
        a = self._action_onehot(action)
        x = torch.cat(
            [self._grid(probs), self._grid(next_probs), a[:, :, None, None].expand(n, -1, 8, 8)],
            dim=1,
        )
        return self.posterior_net(x)

    def sample_prior(
        self,
        probs: torch.Tensor,
        action: torch.Tensor,
        deterministic: bool = True,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor | None:
        """``z`` for test-time prediction: the prior mean, or a draw from the prior."""
        if not self.latent_dim:
            return None
        mean, std = self.prior(probs, action)
        if deterministic:
            return mean
        noise = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        return mean + std * noise

    # ------------------------------------------------------------------ public API
    def logits(
        self, pixels: torch.Tensor, action: torch.Tensor, z: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Per-pixel palette logits of the next frame.

        Args:
            pixels: the current frames ``[N, 3, 16, 16]``: uint8, or floats in ``[0, 1]``.
            action: int64 ``[N, 1]`` in ``[0, num_actions)``.
            z: float ``[N, D]`` latent; ``None`` uses the prior mean (deterministic mode).

        Returns:
            float ``[N, K, 16, 16]``.
        """
        pixels = self._check_pixels(pixels)
        n = pixels.shape[0]
        self._check_action(action, (n, 1))
        if z is not None:
            self._check_z(z, n)
        return self.step_logits(self.frame_probs(pixels), action, z)

    forward = logits

    @torch.no_grad()
    def predict(
        self,
        pixels: torch.Tensor,
        action: torch.Tensor,
        deterministic: bool = True,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """The next frames: ``[N, 3, 16, 16]`` and int64 ``[N, 1]`` -> uint8 ``[N, 3, 16, 16]``.

        Args:
            pixels: current frames: uint8, or floats in ``[0, 1]`` (any precision).
            action: one action per frame, in ``[0, num_actions)``.
            deterministic: use the prior mean of ``z`` (else draw ``z`` from the prior).
            generator: random generator for the draws (default: torch's global one).
        """
        pixels = self._check_pixels(pixels)
        n = pixels.shape[0]
        self._check_action(action, (n, 1))
        probs = self.frame_probs(pixels)
        z = self.sample_prior(probs, action, deterministic, generator)
        return self.frames_from_logits(self.step_logits(probs, action, z))

    @torch.no_grad()
    def rollout(
        self,
        pixels: torch.Tensor,
        actions: torch.Tensor,
        deterministic: bool = True,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Open-loop frames: uint8 ``[N, 3, 16, 16]``, int64 ``[N, H, 1]`` -> uint8 ``[N, H, 3, 16, 16]``.

        Each step feeds on the previous predicted frame (its per-pixel argmax).
        """
        pixels = self._check_pixels(pixels)
        n = pixels.shape[0]
        if not isinstance(actions, torch.Tensor) or actions.dim() != 3:
            got = (
                list(actions.shape) if isinstance(actions, torch.Tensor) else type(actions).__name__
            )
            raise ValueError(f"actions must be an int64 tensor [N, H, 1] with N = {n}, got {got}.")
        horizon = actions.shape[1]
        self._check_action(actions, (n, horizon, 1), name="actions")
        probs = self.frame_probs(pixels)
        frames = []
        for h in range(horizon):
            action = actions[:, h]
            z = self.sample_prior(probs, action, deterministic, generator)
            index = self.step_logits(probs, action, z).argmax(1)
            frames.append(self.frames_from_index(index))
            probs = F.one_hot(index, self.num_colours).movedim(-1, -3).to(probs.dtype)
        if not frames:
            return pixels.new_zeros(n, 0, *FRAME_SHAPE)
        return torch.stack(frames, dim=1)

    def as_tensordict_module(
        self,
        in_keys: tuple[Any, Any] = ("pixels", "action"),
        out_key: Any = ("next", "pixels"),
        deterministic: bool = True,
    ) -> TensorDictModule:
        """This model as a ``TensorDictModule``: ``pixels``, ``action`` -> ``("next", "pixels")``.

        Any leading batch shape works (it is flattened around :meth:`predict`).
        """
        return TensorDictModule(
            _PredictModule(self, deterministic), in_keys=list(in_keys), out_keys=[out_key]
        )

    def extra_repr(self) -> str:
        return f"num_actions={self.num_actions}, palette={self.palette.tolist()}"


class _PredictModule(nn.Module):
    """``predict`` over any leading shape, for :meth:`VideoPredictionModel.as_tensordict_module`."""

    def __init__(self, model: VideoPredictionModel, deterministic: bool) -> None:
        super().__init__()
        self.model = model
        self.deterministic = deterministic

    def forward(self, pixels: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        lead = pixels.shape[:-3]
        out = self.model.predict(
            pixels.reshape(-1, *FRAME_SHAPE), action.reshape(-1, 1), self.deterministic
        )
        return out.reshape(*lead, *FRAME_SHAPE)
