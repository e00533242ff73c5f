"""A latent world model for any frames: encode once, step a latent, read DORP's codes off it.

:class:`LatentWorldModel` encodes a frame ``[C, H, W]`` (uint8, or float in ``[0, 1]``)
into a latent vector, advances the latent with each action (a residual MLP on the latent
and the action's one-hot), reads the codes of a DORP encoder off any latent with a code
head (logits per one-hot), and decodes a latent into a frame where pixels are needed. No
palette is assumed: the decoder predicts each channel's intensity.

Planning with it needs no pixels: a waypoint plan's :class:`~dorp_rl.planners.CodeMatchCost`
reads the imagined codes directly. :meth:`LatentWorldModel.as_world_model` gives the same
parts as torchrl's :class:`~torchrl.modules.WorldModel` (TensorDict modules over
``pixels``, ``latent``, ``action``, ``code``), which
:class:`~dorp_rl.envs.LatentModelEnv` drives as a planning env.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import WorldModel

from dorp_rl.config import Choice, ConfigMixin, Flag, Int, Ints, Text, checked
from dorp_rl.frames import frames_to_unit_float
from dorp_rl.modules.encoder import choose_map_stride, pool_blocks

__all__ = ["LatentModelConfig", "LatentWorldModel"]


@dataclass
class LatentModelConfig(ConfigMixin):
    """Sizes of a :class:`LatentWorldModel`.

    Examples:
        >>> from dorp_rl.modules import LatentModelConfig
        >>> LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(16, 2)).latent_dim
        128
    """

    frame_shape: tuple[int, int, int] = checked(
        (3, 16, 16), Ints(low=1, min_length=3, max_length=3)
    )
    """(C, H, W) of the frames"""
    code_sizes: tuple[int, ...] = checked((32,), Ints(low=2))
    """codes of each one-hot of the DORP encoder whose codes the code head predicts"""
    latent_dim: int = checked(128, Int(low=1))
    """width of a continuous latent state (latent_groups=0, slot_dim=0)"""
    latent_groups: int = checked(0, Int(low=0))
    """0: a continuous latent; > 0: the latent is that many categorical variables of
    latent_classes values each (hard one-hots, trained straight through), so a step's
    small error is snapped away instead of carried into the next"""
    latent_classes: int = checked(16, Int(low=2))
    """values of each categorical latent variable (latent_groups > 0)"""
    slot_dim: int = checked(0, Int(low=0))
    """0: one latent vector stepped by one MLP; > 0: one slot of this width per one-hot
    (the latent is their concatenation), each one-hot's codes read off its own slot only,
    and each slot stepped by one shared update from its slot, the action and messages
    from every other slot (objects that move alike wherever they are; collisions as
    pairwise messages), MLPs of ``hidden`` units with two hidden layers each"""
    dynamics_kind: str = checked("mlp", Choice(("mlp", "conv")))
    """'mlp': the latent is one vector stepped by an MLP; 'conv': the latent is a map of
    ``latent_channels`` x H/s x W/s (s = ``latent_stride``) stepped by convolutions
    that see the action at every cell and the map's mean (effects far away, a door
    opened by a key), so what an object does somewhere it does anywhere"""
    latent_channels: int = checked(32, Int(low=1))
    """channels of the latent map and of the convolutions stepping it (dynamics_kind
    'conv'; their cost grows with its square, so keep it small)"""
    frame_stride: int | None = checked(None, Int(low=1, optional=True))
    """the model reads frames averaged over s x s blocks and decodes frames of that
    resolution, repeated back to the frame's (each s x s block one value); 1 keeps every
    pixel; None: :func:`~dorp_rl.modules.choose_map_stride` of the frame size (1 up to
    31 pixels a side)"""
    latent_stride: int = checked(4, Choice((1, 2, 4)))
    """downsampling of the latent map against the frame (dynamics_kind 'conv')"""
    dynamics_channels: int | None = checked(None, Int(low=1, optional=True))
    """hidden channels of the convolutions stepping a latent map (None: latent_channels)"""
    channels: int = checked(32, Int(low=1))
    """width of the frame encoder's and decoder's convolutions"""
    hidden: int = checked(256, Int(low=1))
    """hidden width of the dynamics and code-head MLPs"""
    dynamics_layers: int = checked(2, Int(low=1))
    """hidden layers of the dynamics MLP, or 3x3 convolutions stepping a latent map (each
    adds a cell to how far the next map sees)"""
    action_planes: bool = checked(True, Flag())
    """dynamics_kind 'conv': the action enters the first convolution as one-hot planes
    (True) or as a learned vector per action added to its output at every cell (False:
    the same away from the map's borders, and cheaper the more actions there are)"""
    decoder: bool = checked(True, Flag())
    """whether the model decodes latents into frames (VF, the goal-image phase, pictures)"""
    decoder_kind: str = checked("conv", Choice(("conv", "mlp")))
    """'conv': transposed convolutions from a ``channels`` x H/4 x W/4 map; 'mlp': one
    hidden layer of ``decoder_hidden`` units to every pixel, several times faster to run
    (a planning call decodes every imagined frame its costs read)"""
    decoder_hidden: int = checked(256, Int(low=1))
    """hidden units of the MLP decoder (decoder_kind 'mlp')"""
    encoder_digest: str | None = checked(None, Text(optional=True))
    """:func:`~dorp_rl.integrity.state_digest` of the DORP encoder whose codes the code
    head learned (set by the trainer), so that a policy with another encoder of the same
    code sizes encodes decoded frames instead of reading these codes; None: unknown"""

    @classmethod
    def recipe(cls, **overrides: Any) -> LatentModelConfig:
        """What the latent world model trainer builds unless told otherwise: a latent map
        stepped by convolutions (what an object does in one place it does in another) and
        an MLP decoder of 1024 units (several times faster to run than transposed
        convolutions), measured on every env of the project."""
        values = {"dynamics_kind": "conv", "decoder_kind": "mlp", "decoder_hidden": 1024}
        return cls(**{**values, **overrides})


class _SlotNorm(nn.Module):
    """A LayerNorm of each of ``slots`` slots of width ``width`` in a flat ``[*B, K * D]``."""

    def __init__(self, slots: int, width: int) -> None:
        super().__init__()
        self.slots, self.width = slots, width
        self.norm = nn.LayerNorm(width)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return self.norm(latent.unflatten(-1, (self.slots, self.width))).flatten(-2)


class _SlotDynamics(nn.Module):
    """The change of each of ``K`` slots ``[*B, K, D]`` after an action: a shared MLP of the
    slot, its index, the action's one-hot and the sum of messages from the other slots
    (a shared MLP of each ordered pair of slots)."""

    def __init__(self, slots: int, width: int, num_actions: int, hidden: int) -> None:
        super().__init__()
        self.slots, self.num_actions = slots, num_actions
        self.message = nn.Sequential(
            nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.update = nn.Sequential(
            nn.Linear(width + hidden + num_actions + slots, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, width),
        )
        self.register_buffer("ids", torch.eye(slots), persistent=False)
        self.register_buffer("others", 1.0 - torch.eye(slots), persistent=False)

    def forward(self, slots: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        k = self.slots
        pairs = torch.cat(
            [
                slots.unsqueeze(-2).expand(*slots.shape[:-2], k, k, slots.shape[-1]),
                slots.unsqueeze(-3).expand(*slots.shape[:-2], k, k, slots.shape[-1]),
            ],
            -1,
        )  # [*B, K (receiver), K (sender), 2D]
        messages = (self.message(pairs) * self.others.unsqueeze(-1)).sum(-2)
        one_hot = nn.functional.one_hot(action.long(), self.num_actions).to(slots.dtype)
        lead = slots.shape[:-2]
        inputs = [
            slots,
            messages,
            one_hot.unsqueeze(-2).expand(*lead, k, self.num_actions),
            self.ids.expand(*lead, k, k),
        ]
        return self.update(torch.cat(inputs, -1))


def _downsampled(size: int, halvings: int = 2) -> int:
    """Side of a feature map after ``halvings`` stride-2 convolutions (kernel 3, padding 1)."""
    for _ in range(halvings):
        size = (size + 1) // 2
    return size


class _ConvDynamics(nn.Module):
    """The change of a latent map ``[*B, S, h, w]`` after an action: ``layers`` 3x3
    convolutions of the map, with the action at every cell and the map's mean (through a
    linear layer, added to every cell) after the first, then a 1x1 convolution back to
    ``S`` channels. The action enters as one-hot planes of the first convolution's input
    (``action_planes``) or as a learned vector per action added to its output at every
    cell: the same function away from the map's borders, far cheaper with many actions.
    The convolutions run channels-last, which oneDNN runs up to twice as fast on a CPU."""

    def __init__(
        self,
        channels: int,
        num_actions: int,
        hidden: int,
        *,
        layers: int = 2,
        action_planes: bool = True,
    ) -> None:
        super().__init__()
        self.num_actions = num_actions
        planes = num_actions if action_planes else 0
        self.first = nn.Conv2d(channels + planes, hidden, 3, padding=1)
        self.action = None if action_planes else nn.Embedding(num_actions, hidden)
        self.mean = nn.Linear(channels, hidden)
        self.second = nn.Conv2d(hidden, hidden, 3, padding=1) if layers > 1 else None
        self.more = nn.ModuleList(
            nn.Conv2d(hidden, hidden, 3, padding=1) for _ in range(layers - 2)
        )
        self.out = nn.Conv2d(hidden, channels, 1)

    def forward(self, latent: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        latent = latent.contiguous(memory_format=torch.channels_last)
        if self.action is None:
            one_hot = nn.functional.one_hot(action.long(), self.num_actions).to(latent.dtype)
            planes = one_hot[..., None, None].expand(*one_hot.shape, *latent.shape[-2:])
            x = self.first(torch.cat([latent, planes], -3))
        else:
            x = self.first(latent) + self.action(action.long())[..., None, None]
        x = x + self.mean(latent.mean((-2, -1)))[..., None, None]
        for conv in (self.second, *self.more):
            if conv is not None:
                x = conv(torch.relu(x))
        return self.out(torch.relu(x)).contiguous()


class LatentWorldModel(nn.Module):
    """Frame encoder, latent dynamics, code head and (optional) decoder.

    Args:
        num_actions: discrete actions (indices ``0 .. num_actions - 1``).
        config: the sizes (:class:`LatentModelConfig`).

    Shapes: ``encode`` ``[*B, C, H, W] -> [*B, D]``; ``step`` ``([*B, D], [*B]) -> [*B, D]``;
    ``code_logits`` ``[*B, D] -> [*B, sum(code_sizes)]``; ``codes`` ``-> [*B, K]`` int64;
    ``decode`` ``[*B, D] -> [*B, C, H, W]`` float in ``[0, 1]``.

    Examples:
        >>> import torch
        >>> from dorp_rl.modules import LatentModelConfig, LatentWorldModel
        >>> model = LatentWorldModel(4, LatentModelConfig(frame_shape=(1, 8, 8), code_sizes=(5,)))
        >>> z = model.encode(torch.zeros(2, 1, 8, 8, dtype=torch.uint8))
        >>> model.codes(model.step(z, torch.tensor([0, 3]))).shape, model.decode(z).shape
        (torch.Size([2, 1]), torch.Size([2, 1, 8, 8]))
    """

    def __init__(self, num_actions: int, config: LatentModelConfig | None = None) -> None:
        super().__init__()
        config = LatentModelConfig() if config is None else config
        if not isinstance(config, LatentModelConfig):
            raise ValueError(f"config must be a LatentModelConfig, got {type(config).__name__}.")
        if int(num_actions) < 1:
            raise ValueError(f"num_actions must be >= 1, got {num_actions}.")
        self.config = config
        self.num_actions = int(num_actions)
        self.code_sizes = tuple(config.code_sizes)
        if config.frame_stride is None:
            config = config.replace(frame_stride=choose_map_stride(tuple(config.frame_shape)))
            self.config = config
        #: frames are averaged over frame_stride x frame_stride blocks before the encoder
        self.frame_stride = int(config.frame_stride)
        c, full_h, full_w = config.frame_shape
        h, w = (math.ceil(d / self.frame_stride) for d in (full_h, full_w))
        #: (C, h, w) of the frames the model reads and decodes
        self.model_frame_shape = (c, h, w)
        self.discrete = config.latent_groups > 0
        #: slots of the latent (one per one-hot), 0 for one latent vector
        self.slots = len(self.code_sizes) if config.slot_dim > 0 else 0
        if self.slots and self.discrete:
            raise ValueError(
                "slot_dim > 0 needs a continuous latent: set latent_groups=0 or slot_dim=0."
            )
        ch = config.channels
        halvings = {1: 0, 2: 1, 4: 2}[config.latent_stride]  # stride-2 convolutions
        #: the latent map's shape (S, h, w) of a convolutional latent, else None
        self.latent_map: tuple[int, int, int] | None = None
        if config.dynamics_kind == "conv":
            if self.slots or self.discrete:
                raise ValueError(
                    "dynamics_kind='conv' steps a continuous latent map: set slot_dim=0 "
                    "and latent_groups=0."
                )
            self.latent_map = (
                config.latent_channels,
                _downsampled(h, halvings),
                _downsampled(w, halvings),
            )
            d = self.latent_map[0] * self.latent_map[1] * self.latent_map[2]
        elif self.discrete:
            d = config.latent_groups * config.latent_classes
        else:
            d = self.slots * config.slot_dim if self.slots else config.latent_dim
        #: size of the latent vector
        self.latent_width = d
        self._feature_shape = (ch, _downsampled(h), _downsampled(w))
        flat = ch * self._feature_shape[1] * self._feature_shape[2]
        # conv, then stride-2 convolutions (two for a latent vector); a map latent ends
        # in a 1x1 convolution to its channels, a vector in a linear layer
        trunk: list[nn.Module] = [nn.Conv2d(c, ch, 3, padding=1), nn.ReLU()]
        for _ in range(halvings if self.latent_map is not None else 2):
            trunk += [nn.Conv2d(ch, ch, 3, stride=2, padding=1), nn.ReLU()]
        if self.latent_map is not None:
            trunk += [nn.Conv2d(ch, config.latent_channels, 1), nn.Flatten()]
        else:
            trunk += [nn.Flatten(), nn.Linear(flat, d)]
        self.frame_encoder = nn.Sequential(*trunk)
        if self.slots:
            sd, hidden = config.slot_dim, config.hidden
            self.encoder_norm: nn.Module = _SlotNorm(self.slots, sd)
            self.dynamics: nn.Module = _SlotDynamics(self.slots, sd, self.num_actions, hidden)
            self.dynamics_norm: nn.Module = _SlotNorm(self.slots, sd)
            self.code_head: nn.Module = nn.ModuleList(
                nn.Sequential(nn.Linear(sd, hidden), nn.ReLU(), nn.Linear(hidden, size))
                for size in self.code_sizes
            )
        else:
            self.encoder_norm = nn.Identity() if self.discrete else nn.LayerNorm(d)
            if self.latent_map is not None:
                self.dynamics = _ConvDynamics(
                    config.latent_channels,
                    self.num_actions,
                    config.dynamics_channels or config.latent_channels,
                    layers=config.dynamics_layers,
                    action_planes=config.action_planes,
                )
            else:
                layers: list[nn.Module] = []
                width = d + self.num_actions
                for _ in range(config.dynamics_layers):
                    layers += [nn.Linear(width, config.hidden), nn.ReLU()]
                    width = config.hidden
                layers.append(nn.Linear(width, d))
                self.dynamics = nn.Sequential(*layers)
            self.dynamics_norm = nn.LayerNorm(d)
            self.code_head = nn.Sequential(
                nn.Linear(d, config.hidden),
                nn.ReLU(),
                nn.Linear(config.hidden, sum(self.code_sizes)),
            )
        self.frame_decoder: nn.Module | None = None
        if config.decoder and config.decoder_kind == "mlp":
            hidden = config.decoder_hidden
            self.decoder_input = nn.Linear(d, hidden)
            self.frame_decoder = nn.Sequential(nn.ReLU(), nn.Linear(hidden, c * h * w))
        elif config.decoder:
            self.decoder_input = nn.Linear(d, flat)
            self.frame_decoder = nn.Sequential(
                nn.ReLU(),
                nn.ConvTranspose2d(ch, ch, 4, stride=2, padding=1),
                nn.ReLU(),
                nn.ConvTranspose2d(ch, ch, 4, stride=2, padding=1),
                nn.ReLU(),
                nn.Conv2d(ch, c, 3, padding=1),
            )

    # ------------------------------------------------------------------ parts
    @property
    def frame_shape(self) -> tuple[int, int, int]:
        return tuple(self.config.frame_shape)

    def encode_logits(self, pixels: torch.Tensor) -> torch.Tensor:
        """The frame encoder's output ``[*B, D]`` before normalisation or quantisation."""
        lead = pixels.shape[:-3]
        x = frames_to_unit_float(pixels).reshape(-1, *pixels.shape[-3:])
        x = pool_blocks(x, self.frame_stride)
        # channels-last: oneDNN runs these small convolutions faster on a CPU
        x = x.contiguous(memory_format=torch.channels_last)
        return self.frame_encoder(x).reshape(*lead, -1)

    def encode(self, pixels: torch.Tensor) -> torch.Tensor:
        """Latents ``[*B, D]`` of frames ``[*B, C, H, W]`` (uint8, or float in [0, 1])."""
        out = self.encode_logits(pixels)
        return self.quantize(out) if self.discrete else self.encoder_norm(out)

    def quantize(self, logits: torch.Tensor) -> torch.Tensor:
        """Hard one-hots of each categorical variable of ``logits`` ``[*B, G * V]``, with
        the softmax's gradient (straight through)."""
        groups = logits.reshape(*logits.shape[:-1], self.config.latent_groups, -1)
        soft = groups.softmax(-1)
        hard = nn.functional.one_hot(soft.argmax(-1), soft.shape[-1]).to(soft.dtype)
        if not torch.is_grad_enabled():
            return hard.reshape(logits.shape)
        return (hard + (soft - soft.detach())).reshape(logits.shape)

    def step_logits(self, latent: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The dynamics' output ``[*B, D]`` for ``action`` (int indices ``[*B]`` or
        ``[*B, 1]``): logits of the next categorical latent, or the continuous latent
        before its normalisation."""
        if action.dim() == latent.dim():
            action = action.squeeze(-1)
        if self.latent_map is not None:
            lead = latent.shape[:-1]
            grid = latent.reshape(-1, *self.latent_map)
            change = self.dynamics(grid, action.reshape(-1))
            return latent + change.reshape(*lead, -1)
        if self.slots:
            slots = latent.unflatten(-1, (self.slots, self.config.slot_dim))
            return latent + self.dynamics(slots, action).flatten(-2)
        one_hot = nn.functional.one_hot(action.long(), self.num_actions).to(latent.dtype)
        out = self.dynamics(torch.cat([latent, one_hot], -1))
        return out if self.discrete else latent + out

    def step(self, latent: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The latent after ``action`` (int indices ``[*B]`` or ``[*B, 1]``)."""
        out = self.step_logits(latent, action)
        return self.quantize(out) if self.discrete else self.dynamics_norm(out)

    def code_logits(self, latent: torch.Tensor) -> torch.Tensor:
        """Logits ``[*B, sum(code_sizes)]`` of each one-hot's code (with slots, one-hot
        ``k``'s from slot ``k`` alone)."""
        if self.slots:
            slots = latent.unflatten(-1, (self.slots, self.config.slot_dim)).unbind(-2)
            heads = zip(self.code_head, slots, strict=True)
            return torch.cat([head(slot) for head, slot in heads], -1)
        return self.code_head(latent)

    def codes(self, latent: torch.Tensor) -> torch.Tensor:
        """The most likely code of each one-hot, int64 ``[*B, K]``."""
        logits = self.code_logits(latent).split(self.code_sizes, dim=-1)
        return torch.stack([part.argmax(-1) for part in logits], -1)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """Frames ``[*B, C, H, W]`` (float in [0, 1]) of latents ``[*B, D]``."""
        if self.frame_decoder is None:
            raise ValueError(
                "this LatentWorldModel has no decoder (LatentModelConfig(decoder=False)): "
                "it predicts codes, not frames."
            )
        lead = latent.shape[:-1]
        x = self.decoder_input(latent.reshape(-1, latent.shape[-1]))
        c, h, w = self.model_frame_shape
        # the sigmoid in float32, whatever the layers ran in (bfloat16 has 8 bits of
        # mantissa: too few for 256 levels)
        if self.config.decoder_kind == "mlp":
            frames = torch.sigmoid(self.frame_decoder(x).float()).reshape(-1, c, h, w)
        else:
            x = self.frame_decoder(x.reshape(-1, *self._feature_shape))
            if tuple(x.shape[-2:]) != (h, w):
                x = nn.functional.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)
            frames = torch.sigmoid(x.float())
        return self._full_size(frames).reshape(*lead, *self.frame_shape)

    def _full_size(self, frames: torch.Tensor) -> torch.Tensor:
        """Decoded ``[N, C, h, w]`` frames repeated back to ``[N, *frame_shape]``."""
        s = self.frame_stride
        if s == 1:
            return frames
        _, height, width = self.frame_shape
        full = frames.repeat_interleave(s, -2).repeat_interleave(s, -1)
        return full[..., :height, :width]

    def decode_uint8(self, latent: torch.Tensor) -> torch.Tensor:
        """:meth:`decode` as uint8 frames (rounded to 0..255)."""
        return (self.decode(latent) * 255.0).round().to(torch.uint8)

    def latent_classes(self, logits: torch.Tensor) -> torch.Tensor:
        """The value int64 ``[*B, G]`` of each categorical variable of ``logits`` (discrete only)."""
        groups = logits.reshape(*logits.shape[:-1], self.config.latent_groups, -1)
        return groups.argmax(-1)

    def imagine(self, latent: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Latents ``[*B, T, D]`` after each of ``actions`` ``[*B, T]`` from ``latent`` ``[*B, D]``."""
        out = []
        for t in range(actions.shape[-1]):
            latent = self.step(latent, actions[..., t])
            out.append(latent)
        return torch.stack(out, -2)

    def forward(self, pixels: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Code logits ``[*B, T, sum(code_sizes)]`` of an open-loop rollout from frames."""
        return self.code_logits(self.imagine(self.encode(pixels), actions))

    # ------------------------------------------------------------------ torchrl
    def as_world_model(
        self, *, decode: bool = False, pixels_key: str = "pixels", latent_key: str = "latent"
    ) -> WorldModel:
        """The model as torchrl's :class:`~torchrl.modules.WorldModel`.

        ``encoder``: ``pixels -> latent``; ``dynamics``: ``(latent, action) ->
        ("next", latent)`` and the codes read off it, ``("next", "code")``; a reward head
        writing 0 (DORP's tasks have none); with ``decode``, a decoder ``("next", latent)
        -> ("next", pixels)`` run at every step.
        """
        model = self

        class _Step(nn.Module):
            def forward(self, latent: torch.Tensor, action: torch.Tensor) -> tuple:
                nxt = model.step(latent, action)
                return nxt, model.codes(nxt)

        class _Zero(nn.Module):
            def forward(self, latent: torch.Tensor) -> torch.Tensor:
                return latent.new_zeros(*latent.shape[:-1], 1)

        class _Decode(nn.Module):
            def forward(self, latent: torch.Tensor) -> torch.Tensor:
                return model.decode_uint8(latent)

        encoder = TensorDictModule(self.encode, in_keys=[pixels_key], out_keys=[latent_key])
        dynamics = TensorDictModule(
            _Step(),
            in_keys=[latent_key, "action"],
            out_keys=[("next", latent_key), ("next", "code")],
        )
        reward = TensorDictModule(
            _Zero(), in_keys=[("next", latent_key)], out_keys=[("next", "reward")]
        )
        decoder = None
        if decode:
            decoder = TensorDictModule(
                _Decode(), in_keys=[("next", latent_key)], out_keys=[("next", pixels_key)]
            )
        return WorldModel(encoder, dynamics, reward, decoder=decoder)

    def extra_repr(self) -> str:
        return f"num_actions={self.num_actions}, {self.config}"


def check_latent_model(model: Any, code_sizes: Sequence[int], frame_shape: Sequence[int]) -> None:
    """Refuses a latent model whose code head or frames do not fit (names both)."""
    if tuple(model.code_sizes) != tuple(code_sizes):
        raise ValueError(
            f"the latent world model predicts codes of sizes {tuple(model.code_sizes)}, the "
            f"encoder has {tuple(code_sizes)}: train it on this encoder's codes."
        )
    if tuple(model.frame_shape) != tuple(frame_shape):
        raise ValueError(
            f"the latent world model takes frames {list(model.frame_shape)}, the env gives "
            f"{list(frame_shape)}."
        )
