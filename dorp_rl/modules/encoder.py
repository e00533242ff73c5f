"""DORP's discrete object-factorized encoder: object extractor, shared per-map encoder, one-hots."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from torch import nn

from dorp_rl.config import Choice, ConfigMixin, Flag, Float, Int, Ints, checked
from dorp_rl.frames import frame_shape_of, frames_to_unit_float
from dorp_rl.validation import as_tensor, check_choice, check_int


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
        ValueError: map_competition must be one of ('auto', 'sigmoid', 'softmax'), got 'max'.
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
    map_competition: str = checked("auto", Choice(("auto", "sigmoid", "softmax")))
    """how object maps share a pixel: sigmoid (independent) or softmax (they compete);
    auto: softmax where two or more one-hots have more than 2 codes (objects), else sigmoid"""
    frame_shape: tuple[int, int, int] = checked(
        (3, 16, 16), Ints(low=1, min_length=3, max_length=3)
    )
    """(C, H, W) of the frames: channels of the first conv; the map encoder reads the maps'
    ceil(H / map_stride) x ceil(W / map_stride) cells"""
    map_stride: int | None = checked(None, Int(low=1, optional=True))
    """the object maps' resolution is the frame's divided by this (each map cell averages a
    map_stride x map_stride block of pixels before the convolutions); 1 keeps every pixel;
    None: :func:`choose_map_stride` of the frame size"""

    subtract_background: bool | None = checked(None, Flag(optional=True))
    """subtract the play frames' static background (their per-pixel median, set by the
    trainer) from every frame, so that only what moves is left; None: no subtraction for
    an encoder built alone, chosen from the play frames by the trainer"""

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Configs stored before the stride and the automatic competition kept every pixel
        and independent maps."""
        values = super().upgrade(values)
        values.setdefault("map_stride", 1)
        values.setdefault("map_competition", "sigmoid")
        values.setdefault("subtract_background", False)
        return values

    def resolved(self) -> EncoderConfig:
        """This config with ``map_competition="auto"``, ``map_stride=None`` and
        ``subtract_background=None`` decided (:func:`competing_maps`,
        :func:`choose_map_stride`, no subtraction)."""
        changes: dict[str, Any] = {}
        if self.map_competition == "auto":
            changes["map_competition"] = "softmax" if competing_maps(self.code_sizes) else "sigmoid"
        if self.map_stride is None:
            changes["map_stride"] = choose_map_stride(self.frame_shape)
        if self.subtract_background is None:
            changes["subtract_background"] = False
        return self.replace(**changes) if changes else self

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


def competing_maps(code_sizes: Sequence[int]) -> bool:
    """Whether object maps should compete for pixels: two or more one-hots of more than 2
    codes (objects; a 2-code one-hot is a flag, such as a key held)."""
    return sum(int(size) > 2 for size in code_sizes) > 1


#: The fewest cells :func:`choose_map_stride` leaves on the maps' shorter side.
MIN_MAP_CELLS = 16
#: The fewest cells a side of the maps at a grid's own resolution (``motion_step``).
MIN_GRID_CELLS = 4
#: The fewest map cells across the smallest object where objects differ in shape alone.
MIN_SHAPE_CELLS = 3


def choose_map_stride(
    frame_shape: tuple[int, int, int],
    smallest_object: int | None = None,
    motion_step: int | None = None,
    shapes_only: bool = False,
) -> int:
    """The :attr:`EncoderConfig.map_stride` for frames of ``frame_shape`` ``(C, H, W)``.

    The largest stride ``s`` that leaves the object maps at least 16 cells on their shorter
    side (``min(H, W) // s >= 16``) and, when ``smallest_object`` (the extent in pixels of
    the smallest moving object) is given, at most that extent, so that an object still
    covers a whole map cell's worth of pixels. Frames of 16 pixels or fewer a side get 1.

    When the objects move on a grid of ``motion_step`` pixels a cell (a grid world drawn
    ``k`` pixels a cell; :attr:`~dorp_rl.data.FrameScan.motion_step`), the stride is one
    the grid's cells fit: the largest multiple of the step within the bounds above, or
    the step itself (maps at the grid's own resolution, at least 4 cells a side) where
    the objects fill their cells. A map cell then never straddles two grid cells, so an
    object in one place always falls on the same map cells.

    With ``shapes_only`` (objects of one colour move:
    :attr:`~dorp_rl.data.FrameScan.pieces_share_colours`) the codes tell them apart by
    shape alone, so the smallest object spans at least 3 map cells, the fewest that show a
    shape (at one cell each, two white dominoes, one lying and one standing, trained maps
    that followed both or neither).

    Code training costs about as much per step at every frame size with it: 64 x 64 frames
    get 16 x 16 maps, 84 x 84 frames 17 x 17 maps.

    Examples:
        >>> from dorp_rl.modules import choose_map_stride
        >>> [choose_map_stride((3, n, n)) for n in (16, 30, 64, 84)]
        [1, 1, 4, 5]
        >>> choose_map_stride((3, 84, 84), smallest_object=3), choose_map_stride((1, 24, 32))
        (3, 1)
        >>> # a 12 x 12 grid drawn 3 pixels a cell; 2 x 2 cells drawn 4 pixels a cell
        >>> choose_map_stride((1, 36, 36), 3, motion_step=3), choose_map_stride((3, 84, 84), 8, 2)
        (3, 4)
        >>> choose_map_stride((1, 36, 36), 3, motion_step=3, shapes_only=True)
        1
    """
    shape = tuple(frame_shape)
    if len(shape) != 3:
        raise ValueError(f"frame_shape must be (C, H, W), got {frame_shape}.")
    _, height, width = (check_int(f"frame_shape[{i}]", d, low=1) for i, d in enumerate(shape))
    side = min(height, width)
    limit = (
        side if smallest_object is None else check_int("smallest_object", smallest_object, low=1)
    )
    if shapes_only:
        limit = max(1, limit // MIN_SHAPE_CELLS)
    stride = min(max(1, side // MIN_MAP_CELLS), limit)
    step = 1 if motion_step is None else check_int("motion_step", motion_step, low=1)
    if 1 < step <= stride:
        stride -= stride % step
    elif step > stride and step <= limit and side // step >= MIN_GRID_CELLS:
        stride = step
    return stride


def module_device(module: nn.Module) -> torch.device:
    """Device of a module's first parameter or buffer (CPU for a module without tensors)."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


@contextmanager
def eval_mode(module: object) -> Iterator[None]:
    """Runs the block with ``module`` in eval mode and restores its mode after (also on
    an error); anything that is not an ``nn.Module`` (a function, ``None``) is left as is.

    Examples:
        >>> from torch import nn
        >>> layer = nn.Dropout().train()
        >>> with eval_mode(layer):
        ...     layer.training
        False
        >>> layer.training
        True
    """
    if not isinstance(module, nn.Module):
        yield
        return
    was_training = module.training
    module.eval()
    try:
        yield
    finally:
        module.train(was_training)


def check_pixels(
    pixels: torch.Tensor, name: str = "pixels", shape: Sequence[int] | None = None
) -> torch.Tensor:
    """Images ``[*B, C, H, W]`` (uint8, or floats in ``[0, 1]``; numpy arrays are taken) as
    floats in ``[0, 1]``; with ``shape``, frames of another ``(C, H, W)`` are refused.

    Float frames outside ``[0, 1]`` (a forgotten ``/ 255``) are refused
    (:func:`dorp_rl.frames.frames_to_unit_float`).
    """
    return frames_to_unit_float(pixels, name, shape=shape)


def pool_blocks(x: torch.Tensor, stride: int, reduce: str = "mean") -> torch.Tensor:
    """Mean (or sum) of ``x`` ``[N, C, H, W]`` over ``stride x stride`` blocks, ``[N, C,
    ceil(H / stride), ceil(W / stride)]``; a partial block at the bottom or right edge
    averages (sums) the pixels it has. ``x`` itself for ``stride`` 1."""
    if stride == 1:
        return x
    divisor = 1 if reduce == "sum" else None
    return F.avg_pool2d(x, stride, stride, ceil_mode=True, divisor_override=divisor)


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
    observation spec. With ``config.map_stride`` ``s > 1`` the frames are first averaged
    over ``s x s`` blocks (the last row and column of blocks may be partial), so the
    convolutions and the maps have ``ceil(H / s) x ceil(W / s)`` cells
    (:attr:`map_shape`): large frames then train about as fast as small ones
    (:func:`choose_map_stride`).

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
        >>> config = EncoderConfig.small((8,), frame_shape=(3, 84, 84), map_stride=5)
        >>> big = DiscreteCodeEncoder(config)  # 84 x 84 frames, 17 x 17 maps
        >>> big.object_maps(torch.zeros(2, 3, 84, 84, dtype=torch.uint8)).shape
        torch.Size([2, 1, 17, 17])
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
        check_choice("map_competition", config.map_competition, ("auto", "sigmoid", "softmax"))
        config = config.resolved()
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
        self.map_stride = check_int("map_stride", config.map_stride, low=1)
        if self.map_stride > min(self.frame_shape[1:]):
            raise ValueError(
                f"map_stride {self.map_stride} is larger than the frames' shorter side "
                f"{min(self.frame_shape[1:])} (frame_shape {self.frame_shape})."
            )
        if config.subtract_background:
            # the static background in [0, 1], [C, H, W] (set_background; zero: none)
            self.register_buffer("background", torch.zeros(self.frame_shape))
        # (h, w) cells of the object maps: ceil(H / map_stride), ceil(W / map_stride)
        self.map_shape = tuple(math.ceil(d / self.map_stride) for d in self.frame_shape[1:])
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
        width = self.map_shape[0] * self.map_shape[1]
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
        (:func:`~dorp_rl.frames.frame_shape_of`)."""
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

    @torch.no_grad()
    def set_background(self, background: torch.Tensor) -> None:
        """Sets the static background subtracted from every frame: uint8 (or floats in
        ``[0, 1]``) ``[C, H, W]``, e.g. :attr:`~dorp_rl.data.FrameScan.background`.

        Raises:
            ValueError: the encoder was built without ``subtract_background``, or the
                background is not one frame of its shape.
        """
        if not self.config.subtract_background:
            raise ValueError("set_background needs an encoder built with subtract_background=True.")
        frame = check_pixels(background, "background", shape=self.frame_shape)
        if frame.dim() != 3:
            raise ValueError(f"background must be one frame {list(self.frame_shape)}.")
        self.background.copy_(frame.to(self.background.device))

    def pool_to_maps(self, x: torch.Tensor, reduce: str = "mean") -> torch.Tensor:
        """``[N, C', H, W]`` frame-sized floats on the maps' cells, ``[N, C', h, w]``
        (:attr:`map_shape`): the mean (or with ``reduce="sum"`` the sum) of each cell's
        ``map_stride x map_stride`` block of pixels, over the pixels a partial block at
        the bottom or right edge has. The identity (the same tensor) for ``map_stride`` 1.
        """
        check_choice("reduce", reduce, ("mean", "sum"))
        return pool_blocks(x, self.map_stride, reduce)

    def object_maps(self, pixels: torch.Tensor) -> torch.Tensor:
        """The extractor's per-one-hot maps, float ``[*B, C, h, w]`` (one per one-hot).

        ``(h, w)`` is :attr:`map_shape`: the frame's ``(H, W)`` for ``map_stride`` 1,
        else ``ceil(H / map_stride), ceil(W / map_stride)``, map cell ``(i, j)`` standing
        for pixels ``[i * s, (i + 1) * s) x [j * s, (j + 1) * s)``.

        In eval mode without gradients (planning, graph building) the extractor runs as
        :meth:`inference_extractor`: the same function, 2-3x faster on a CPU.
        """
        x = check_pixels(pixels, shape=self.frame_shape)
        batch = x.shape[:-3]
        x = x.reshape(-1, *self.frame_shape)
        if self.config.subtract_background:
            x = x - self.background
        if self.map_stride > 1:
            # pool before scaling: the same up to rounding, on s^2 fewer values
            x = pool_blocks(x, self.map_stride, "mean")
        x = x * self.config.input_scale
        if self.training or torch.is_grad_enabled() or not self.fast_inference:
            out = self.extractor(x)
        else:
            fast = self.inference_extractor()
            out = fast(x.contiguous(memory_format=torch.channels_last)).contiguous()
        if self.config.map_competition == "softmax":
            out = out.softmax(dim=1)[:, : self.num_onehots]
        else:
            out = out.sigmoid()
        return out.reshape(*batch, self.num_onehots, *self.map_shape)

    def inference_extractor(self) -> nn.Module:
        """The extractor for inference: BatchNorm folded into the convolutions, channels-last.

        Equal to the extractor in eval mode up to float rounding (about 1e-6 relative),
        and 2-3x faster on a CPU, where oneDNN prefers channels-last inputs. Like
        :attr:`extractor`, it takes the frames already pooled to the maps' cells
        (:meth:`pool_to_maps`; nothing to pool for ``map_stride`` 1). Built on
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
        """Code logits ``[*B, C, Z]`` (``-inf`` on masked codes) and the maps ``[*B, C, h, w]``
        (:meth:`object_maps`)."""
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
        with eval_mode(self):
            device = self.code_mask.device
            pixels = as_tensor(pixels, "pixels")
            flat = pixels.reshape(-1, *pixels.shape[-3:])
            codes = [self(chunk.to(device))[0] for chunk in flat.split(chunk_size)]
            return torch.cat(codes).reshape(*pixels.shape[:-3], self.num_onehots)

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
