"""DORP's discrete object-factorized encoder: object extractor, shared per-map encoder, one-hots."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from dorp_rl.config import ConfigMixin, checked
from dorp_rl.validation import (
    Choice,
    Float,
    Int,
    Ints,
    as_tensor,
    check_choice,
    check_int,
    frame_shape_of,
    frames_to_unit_float,
)


@dataclass
class EncoderConfig(ConfigMixin):
    """Sizes of :class:`DiscreteCodeEncoder`.

    Use :meth:`small` (what the trainer presets use) or :meth:`authors` (the authors'
    release), then override fields. In a
    :class:`~dorp_rl.trainers.RepresentationConfig`, ``code_sizes`` may be one number:
    the size of every object one-hot, laid out by the environment.

    Examples:
        >>> from dorp_rl.modules import EncoderConfig
        >>> cfg = EncoderConfig.small((16, 2))  # an agent one-hot and a key bit
        >>> cfg.code_sizes, EncoderConfig.from_dict(cfg.to_dict()) == cfg
        ((16, 2), True)
        >>> cfg.replace(map_competition="max")
        Traceback (most recent call last):
        ...
        ValueError: map_competition must be one of ('sigmoid', 'softmax'), got 'max'.
    """

    code_sizes: tuple[int, ...] = checked((32,), Ints(low=2))
    """codes of each one-hot, e.g. (32, 32) for two objects, (16, 2) for agent and key bit"""
    channels: int = checked(32, Int(low=1))
    """width of the object extractor's convolutions"""
    conv_layers: int = checked(3, Int(low=0))
    """hidden conv + BatchNorm + ReLU layers of the object extractor"""
    kernel_size: int = checked(3, Int(low=1))
    """the extractor's conv kernel size (odd; 1: each map sees only its own pixels)"""
    mlp_sizes: tuple[int, ...] = checked((512, 512), Ints(low=1, min_length=0))
    """hidden widths of the per-map encoder shared by all maps (the last gets a LayerNorm)"""
    input_scale: float = checked(10.0, Float(low=0.0, low_open=True))
    """pixels in [0, 1] are multiplied by this"""
    map_competition: str = checked("sigmoid", Choice(("sigmoid", "softmax")))
    """how object maps share a pixel: sigmoid (independent) or softmax (they compete)"""
    frame_shape: tuple[int, int, int] = checked(
        (3, 16, 16), Ints(low=1, min_length=3, max_length=3)
    )
    """(C, H, W) of the frames: channels of the first conv, H x W inputs of the map encoder"""

    @classmethod
    def authors(cls, code_sizes: Sequence[int] = (32,), **overrides: Any) -> EncoderConfig:
        """The authors' release: 32 channels, per-map MLP 256-512-512-Z."""
        return cls(code_sizes=tuple(code_sizes), **overrides)

    @classmethod
    def small(cls, code_sizes: Sequence[int] = (32,), **overrides: Any) -> EncoderConfig:
        """About 3x faster on a 2-core CPU: 16 channels, per-map MLP 256-128-128-Z."""
        values = {"channels": 16, "mlp_sizes": (128, 128), **overrides}
        return cls(code_sizes=tuple(code_sizes), **values)

    def check_relations(self) -> None:
        if self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be an odd int >= 1, got {self.kernel_size}.")


def module_device(module: nn.Module) -> torch.device:
    """Device of a module's first parameter or buffer (CPU for a module without tensors)."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


def check_pixels(
    pixels: torch.Tensor, name: str = "pixels", shape: Sequence[int] | None = None
) -> torch.Tensor:
    """Images ``[*B, C, H, W]`` (uint8, or floats in ``[0, 1]``; numpy arrays are taken) as
    floats in ``[0, 1]``; with ``shape``, frames of another ``(C, H, W)`` are refused.

    Float frames outside ``[0, 1]`` (a forgotten ``/ 255``) are refused
    (:func:`dorp_rl.validation.frames_to_unit_float`).
    """
    return frames_to_unit_float(pixels, name, shape=shape)


class DiscreteCodeEncoder(nn.Module):
    """Maps images to C discrete codes, one per one-hot (ideally one per object).

    A CNN object extractor turns the image into C feature maps (one per one-hot); one
    MLP shared by all maps turns each map into the logits of its one-hot. One-hots may
    have different sizes: the shared head outputs ``max(code_sizes)`` logits and the
    extra ones of a smaller one-hot are masked out.

    ``forward(pixels)`` returns ``(code, code_probs)``: int64 ``[*B, C]`` (argmax of the
    logits, as the authors' inference) and float ``[*B, C, Z]`` (softmax, zero on masked
    codes). :meth:`logits` gives the raw ``[*B, C, Z]`` logits (``-inf`` where masked)
    for training. :meth:`as_tensordict_module` wraps it as a ``TensorDictModule``.

    Frames of any ``(C, H, W)`` are taken: ``config.frame_shape`` sizes the first
    convolution and the map encoder, and :meth:`for_env` reads it off an env's
    observation spec.

    Args:
        config: sizes (see :class:`EncoderConfig`).

    Examples:
        >>> import torch
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(16, 2)))
        >>> pixels = torch.randint(0, 256, (4, 3, 16, 16), dtype=torch.uint8)
        >>> code, probs = encoder(pixels)
        >>> code.shape, probs.shape
        (torch.Size([4, 2]), torch.Size([4, 2, 16]))
        >>> bool((code[:, 1] < 2).all())  # the key bit only uses 2 codes
        True
        >>> gray = DiscreteCodeEncoder(EncoderConfig.small((8,), frame_shape=(1, 24, 32)))
        >>> gray.encode(torch.zeros(5, 1, 24, 32, dtype=torch.uint8)).shape
        torch.Size([5, 1])
    """

    env_config: dict | None = None
    """``env.config()`` of the environment the encoder was trained on (set by
    :class:`~dorp_rl.trainers.RepresentationTrainer` and ``load_encoder``; ``None``:
    unknown). A code graph refuses play data of another environment by it."""

    fast_inference: bool = True
    """Run :meth:`inference_extractor` in eval mode without gradients (set ``False`` on
    an instance to time or debug the plain extractor)."""

    def __init__(self, config: EncoderConfig) -> None:
        super().__init__()
        sizes = tuple(
            check_int(f"code_sizes[{i}]", z, low=2) for i, z in enumerate(config.code_sizes)
        )
        if not sizes:
            raise ValueError(f"code_sizes needs at least one one-hot of >= 2 codes, got {sizes}.")
        check_choice("map_competition", config.map_competition, ("sigmoid", "softmax"))
        self.config = config
        self.code_sizes = sizes
        self.num_onehots = len(sizes)
        self.max_codes = max(sizes)
        k = check_int("kernel_size", config.kernel_size, low=1)
        if k % 2 == 0:
            raise ValueError(f"kernel_size must be an odd int >= 1, got {config.kernel_size}.")
        check_int("channels", config.channels, low=1)
        check_int("conv_layers", config.conv_layers, low=0)
        for i, width in enumerate(config.mlp_sizes):
            check_int(f"mlp_sizes[{i}]", width, low=1)
        self.frame_shape = tuple(
            check_int(f"frame_shape[{i}]", d, low=1) for i, d in enumerate(config.frame_shape)
        )
        if len(self.frame_shape) != 3:
            raise ValueError(f"frame_shape must be (C, H, W), got {config.frame_shape}.")
        layers: list[nn.Module] = []
        in_channels = self.frame_shape[0]
        for _ in range(config.conv_layers):
            layers += [
                nn.Conv2d(in_channels, config.channels, k, padding=k // 2),
                nn.BatchNorm2d(config.channels),
                nn.ReLU(),
            ]
            in_channels = config.channels
        extra = 1 if config.map_competition == "softmax" else 0
        layers.append(nn.Conv2d(in_channels, self.num_onehots + extra, k, padding=k // 2))
        self.extractor = nn.Sequential(*layers)
        mlp: list[nn.Module] = []
        width = self.frame_shape[1] * self.frame_shape[2]
        for i, hidden in enumerate(config.mlp_sizes):
            mlp.append(nn.Linear(width, hidden))
            if i == len(config.mlp_sizes) - 1:
                mlp.append(nn.LayerNorm(hidden))
            mlp.append(nn.ReLU())
            width = hidden
        mlp.append(nn.Linear(width, self.max_codes))
        self.map_encoder = nn.Sequential(*mlp)
        mask = torch.zeros(self.num_onehots, self.max_codes, dtype=torch.bool)
        for i, size in enumerate(sizes):
            mask[i, size:] = True
        self.register_buffer("code_mask", mask, persistent=False)
        self.reset_parameters()

    @classmethod
    def for_env(
        cls, env: Any, config: EncoderConfig | None = None, key: Any = "pixels"
    ) -> DiscreteCodeEncoder:
        """An encoder of ``env``'s frames: ``config`` (default :meth:`EncoderConfig.small`)
        with ``frame_shape`` read off the observation spec of ``key``
        (:func:`~dorp_rl.validation.frame_shape_of`)."""
        config = EncoderConfig.small() if config is None else config
        return cls(config.replace(frame_shape=frame_shape_of(env, key)))

    def reset_parameters(self) -> None:
        """Xavier-uniform weights and zero biases (the authors' initialisation)."""
        for module in self.modules():
            if isinstance(module, (nn.Conv2d, nn.Linear)):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)
            elif isinstance(module, (nn.BatchNorm2d, nn.LayerNorm)):
                module.reset_parameters()

    def object_maps(self, pixels: torch.Tensor) -> torch.Tensor:
        """The extractor's per-one-hot maps, float ``[*B, C, H, W]`` (one per one-hot).

        In eval mode without gradients (planning, graph building) the extractor runs as
        :meth:`inference_extractor`: the same function, 2-3x faster on a CPU.
        """
        x = check_pixels(pixels, shape=self.frame_shape) * self.config.input_scale
        batch = x.shape[:-3]
        x = x.reshape(-1, *self.frame_shape)
        if self.training or torch.is_grad_enabled() or not self.fast_inference:
            out = self.extractor(x)
        else:
            fast = self.inference_extractor()
            out = fast(x.contiguous(memory_format=torch.channels_last)).contiguous()
        if self.config.map_competition == "softmax":
            out = out.softmax(dim=1)[:, : self.num_onehots]
        else:
            out = out.sigmoid()
        return out.reshape(*batch, self.num_onehots, *self.frame_shape[1:])

    def inference_extractor(self) -> nn.Module:
        """The extractor for inference: BatchNorm folded into the convolutions, channels-last.

        Equal to the extractor in eval mode up to float rounding (about 1e-6 relative),
        and 2-3x faster on a CPU, where oneDNN prefers channels-last inputs. Built on
        first use and rebuilt whenever a weight or running statistic changes (training
        steps, ``load_state_dict``, moving to another device); it is not a submodule, so
        it never enters the state dict.
        """
        tensors = self.extractor.state_dict(keep_vars=True).values()
        stamp = tuple((t.data_ptr(), t._version, t.device) for t in tensors)
        cached = self.__dict__.get("_inference_extractor")
        if cached is not None and cached[0] == stamp:
            return cached[1]
        layers: list[nn.Module] = []
        modules = list(self.extractor)
        with torch.no_grad():
            for i, module in enumerate(modules):
                if isinstance(module, nn.BatchNorm2d):
                    continue
                if isinstance(module, nn.Conv2d):
                    conv = nn.Conv2d(
                        module.in_channels,
                        module.out_channels,
                        module.kernel_size,
                        padding=module.padding,
                    ).to(module.weight.device)
                    weight, bias = module.weight.detach(), module.bias.detach()
                    following = modules[i + 1] if i + 1 < len(modules) else None
                    if isinstance(following, nn.BatchNorm2d):
                        scale = following.weight / torch.sqrt(following.running_var + following.eps)
                        weight = weight * scale.view(-1, 1, 1, 1)
                        bias = (bias - following.running_mean) * scale + following.bias
                    conv.weight.copy_(weight)
                    conv.bias.copy_(bias)
                    layers.append(conv)
                elif isinstance(module, nn.ReLU):
                    layers.append(nn.ReLU(inplace=True))
                else:
                    raise TypeError(f"unexpected extractor layer {type(module).__name__}.")
        fast = nn.Sequential(*layers).eval().to(memory_format=torch.channels_last)
        for parameter in fast.parameters():
            parameter.requires_grad_(False)
        # A plain attribute (a tuple), not a submodule: no state dict entry, no `.to()`.
        self.__dict__["_inference_extractor"] = (stamp, fast)
        return fast

    def __getstate__(self) -> dict[str, Any]:
        state = dict(super().__getstate__())
        state.pop("_inference_extractor", None)  # rebuilt on first use
        return state

    @torch.no_grad()
    def permute_onehots_(self, order: Sequence[int]) -> None:
        """Gives one-hot ``i`` the object map one-hot ``order[i]`` had; code sizes stay put.

        Permutes the output channels of the extractor's last convolution (a softmax
        background channel stays last), so one-hot ``i`` now codes what ``order[i]``
        coded, within its own code size.
        """
        order = [int(i) for i in order]
        if sorted(order) != list(range(self.num_onehots)):
            raise ValueError(
                f"order must be a permutation of range({self.num_onehots}), got {order}."
            )
        last = self.extractor[-1]
        index = torch.tensor(order + list(range(self.num_onehots, last.out_channels)))
        index = index.to(last.weight.device)
        last.weight.copy_(last.weight[index])
        last.bias.copy_(last.bias[index])

    def logits_and_maps(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Code logits ``[*B, C, Z]`` (``-inf`` on masked codes) and the maps ``[*B, C, H, W]``."""
        maps = self.object_maps(pixels)
        logits = self.map_encoder(maps.flatten(-2))
        return logits.masked_fill(self.code_mask, float("-inf")), maps

    def logits(self, pixels: torch.Tensor) -> torch.Tensor:
        """Per-one-hot code logits, float ``[*B, C, Z]``, ``-inf`` on masked codes."""
        return self.logits_and_maps(pixels)[0]

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits = self.logits(pixels)
        return logits.argmax(-1), logits.softmax(-1)

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor, chunk_size: int = 4096) -> torch.Tensor:
        """Codes int64 ``[*B, C]`` of many images ``[*B, *frame_shape]``, in eval mode and in chunks.

        Takes what :meth:`forward` takes (uint8 or floats in ``[0, 1]``, tensors or numpy
        arrays).
        """
        was_training = self.training
        self.eval()
        try:
            device = self.code_mask.device
            pixels = as_tensor(pixels, "pixels")
            flat = pixels.reshape(-1, *pixels.shape[-3:])
            codes = [self(chunk.to(device))[0] for chunk in flat.split(chunk_size)]
            return torch.cat(codes).reshape(*pixels.shape[:-3], self.num_onehots)
        finally:
            self.train(was_training)

    def as_tensordict_module(
        self,
        in_key: str = "pixels",
        out_keys: tuple[str, str] = ("code", "code_probs"),
    ) -> TensorDictModule:
        """This encoder as a ``TensorDictModule``: ``pixels`` -> ``code``, ``code_probs``.

        Pass ``in_key="goal_pixels"`` and ``out_keys=("goal_code", "goal_code_probs")``
        to encode goals.
        """
        return TensorDictModule(self, in_keys=[in_key], out_keys=list(out_keys))

    def extra_repr(self) -> str:
        return f"code_sizes={self.code_sizes}, {asdict(self.config)}"
