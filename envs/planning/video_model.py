"""A learned video prediction model as a planning env (:class:`VideoModelEnv`, a torchrl
:class:`~torchrl.envs.model_based.ModelBasedEnvBase`): the next frame from the current
frame and the action, by its world model (:class:`FramePredictorModel`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.model_based import ModelBasedEnvBase

from dorp_rl.envs.grid_base import (
    CheckedRolloutLength,
    describe_foreign_colours,
    foreign_colours,
)
from dorp_rl.envs.planning.base import (
    _FRAME,
    FramePredictor,
    PlanningEnvSpecs,
    check_planning_action,
)
from dorp_rl.envs.planning.frame_hash import _distinct_pairs
from dorp_rl.frames import check_frames, frames_to_uint8
from dorp_rl.validation import (
    check_device,
    check_int,
)

__all__ = [
    "DEFAULT_PREDICT_CHUNK",
    "FramePredictorModel",
    "VideoModelEnv",
]


#: Frames per ``predict`` call of :class:`VideoModelEnv` by default. On one CPU thread the
#: video model predicted a frame in about 0.2 ms in calls of 128-2048 frames and 0.38 ms
#: in calls of 8192 (``benchmarks/predict_chunking.py``); a batched evaluation of 10
#: tasks x 1000 candidates hands it 10,000 at once.
DEFAULT_PREDICT_CHUNK = 1024


class FramePredictorModel(TensorDictModuleBase):
    """The world model of :class:`VideoModelEnv`: a frame predictor as a TensorDict module.

    Reads ``pixels`` and ``action`` and writes the next ``pixels`` (with a zero
    ``reward`` and ``False`` done flags: imagined rollouts run for the whole horizon),
    predicting each distinct (frame, action) pair once when ``deduplicate``, in chunks of
    ``chunk_size`` frames (see :class:`VideoModelEnv` for the arguments).
    """

    def __init__(
        self,
        model: FramePredictor,
        num_actions: int,
        *,
        deterministic: bool = True,
        chunk_size: int | None = DEFAULT_PREDICT_CHUNK,
        deduplicate: bool | None = None,
    ) -> None:
        super().__init__()
        if not callable(getattr(model, "predict", None)):
            raise ValueError(
                f"model must have a predict(pixels, action, deterministic=True) method, "
                f"got {type(model).__name__}."
            )
        if chunk_size is not None and int(chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1 or None, got {chunk_size}.")
        num_actions = check_int("num_actions", num_actions, low=1)
        model_actions = getattr(model, "num_actions", None)
        if isinstance(model_actions, int) and model_actions != num_actions:
            raise ValueError(
                f"num_actions={num_actions} does not match the model, which was trained with "
                f"{model_actions} actions: the planner would plan with the wrong actions. Pass "
                "the acting env's num_actions with a model trained on that env."
            )
        self.model = model
        self.num_actions = num_actions
        self.deterministic = bool(deterministic)
        self.chunk_size = None if chunk_size is None else int(chunk_size)
        if deduplicate and not self.deterministic:
            raise ValueError(
                "deduplicate=True needs deterministic=True: a stochastic model gives "
                "different frames for equal inputs."
            )
        self.deduplicate = self.deterministic if deduplicate is None else bool(deduplicate)
        self.in_keys = ["pixels", "action"]
        self.out_keys = ["pixels", "reward", "done", "terminated", "truncated"]

    def predict_frames(self, pixels: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Next frames for any leading shape: uint8 ``[*B, 3, 16, 16]`` (or floats in ``[0, 1]``),
        int ``[*B, 1]`` -> uint8 ``[*B, 3, 16, 16]``."""
        pixels = frames_to_uint8(pixels, "pixels", shape=_FRAME)
        shape = pixels.shape[:-3]
        action = check_planning_action(action, self.num_actions, shape)
        flat_pixels = pixels.reshape(-1, *_FRAME)
        flat_action = action.reshape(-1, 1)
        inverse = None
        if self.deduplicate and flat_pixels.shape[0] > 1:
            flat_pixels, flat_action, inverse = _distinct_pairs(flat_pixels, flat_action)
        n = flat_pixels.shape[0]
        step = n if self.chunk_size is None else self.chunk_size
        outputs = []
        with torch.no_grad():
            for start in range(0, max(n, 1), max(step, 1)):
                chunk = self.model.predict(
                    flat_pixels[start : start + step],
                    flat_action[start : start + step],
                    deterministic=self.deterministic,
                )
                outputs.append(chunk)
        out = outputs[0] if len(outputs) == 1 else torch.cat(outputs)
        if (
            not isinstance(out, torch.Tensor)
            or out.dtype != torch.uint8
            or tuple(out.shape) != (n, *_FRAME)
        ):
            got = (
                f"{out.dtype} {list(out.shape)}"
                if isinstance(out, torch.Tensor)
                else type(out).__name__
            )
            raise ValueError(
                f"model.predict must return uint8 [{n}, 3, 16, 16] for {n} frames, got {got}."
            )
        if inverse is not None:
            out = out[inverse]
        return out.reshape(*shape, *_FRAME)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        pixels = tensordict.get("pixels", None)
        if pixels is None:
            raise KeyError("VideoModelEnv.step needs 'pixels' (the current frame).")
        shape = tensordict.batch_size
        action = check_planning_action(tensordict.get("action"), self.num_actions, shape)
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=pixels.device)
        tensordict.set("pixels", self.predict_frames(pixels, action))
        tensordict.set("reward", torch.zeros((*shape, 1), device=pixels.device))
        for key in ("done", "terminated", "truncated"):
            tensordict.set(key, false.clone())
        return tensordict


class VideoModelEnv(PlanningEnvSpecs, CheckedRolloutLength, ModelBasedEnvBase):
    """A video prediction model as a planning env: next ``pixels`` from ``pixels`` and ``action``.

    A torchrl :class:`~torchrl.envs.model_based.ModelBasedEnvBase` whose ``world_model``
    is a :class:`FramePredictorModel` around ``model``; stepped by torchrl's own
    ``_step`` (the world model on a shallow copy of the input, its outputs selected by
    the specs).

    ``model`` is any object with ``predict(pixels, action, deterministic=True)``
    mapping uint8 ``[N, 3, 16, 16]`` and int64 ``[N, 1]`` to uint8 ``[N, 3, 16, 16]``
    (:class:`~dorp_rl.modules.VideoPredictionModel` is one). The env flattens the
    leading dimensions before calling it and restores them after, in chunks of
    ``chunk_size`` frames: a ``[B, N]`` batch of 10 x 1000 frames is large for a conv net,
    in memory and in time (per frame, calls of 8192 frames took about twice as long as
    calls of 1024 on a CPU). If ``model`` is an ``nn.Module`` it becomes a submodule, so
    moving a planner moves it; predictions run under ``torch.no_grad()``.

    ``reset(td, set_state=True)`` starts from ``td["pixels"]`` (and keeps
    ``td["goal_pixels"]``); a plain ``reset()`` gives black frames.

    Args:
        model: the frame predictor.
        num_actions: size of the discrete action space.
        deterministic: passed to ``model.predict`` (the mode of a stochastic model).
        chunk_size: at most this many frames per ``predict`` call (default
            :data:`DEFAULT_PREDICT_CHUNK`; ``None``: all at once).
        deduplicate: predict each distinct (frame, action) pair once and copy the result
            to its duplicates (default: on in deterministic mode, where it gives the same
            frames). Planning repeats pairs a lot: at the first imagined step all N
            candidates share one frame, so there are at most ``num_actions`` pairs;
            candidates also share prefixes and blocked moves leave frames unchanged.
        device: where tensors live (defaults to the model's parameters' device, else CPU).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.envs import VideoModelEnv
        >>> class StillModel:  # predicts that nothing moves
        ...     def predict(self, pixels, action, deterministic=True):
        ...         return pixels.clone()
        >>> env = VideoModelEnv(StillModel(), num_actions=4)
        >>> td = TensorDict(
        ...     pixels=torch.zeros(2, 7, 3, 16, 16, dtype=torch.uint8),
        ...     action=torch.zeros(2, 7, 1, dtype=torch.int64),
        ...     batch_size=(2, 7),
        ... )
        >>> env.step(td)["next", "pixels"].shape
        torch.Size([2, 7, 3, 16, 16])
    """

    def __init__(
        self,
        model: FramePredictor,
        num_actions: int,
        *,
        deterministic: bool = True,
        chunk_size: int | None = DEFAULT_PREDICT_CHUNK,
        deduplicate: bool | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        world_model = FramePredictorModel(
            model,
            num_actions,
            deterministic=deterministic,
            chunk_size=chunk_size,
            deduplicate=deduplicate,
        )
        device = check_device(device, optional=True)
        if device is None and isinstance(model, torch.nn.Module):
            param = next(iter(model.parameters()), None)
            device = param.device if param is not None else None
        super().__init__(
            world_model, device=torch.device("cpu") if device is None else device, batch_size=()
        )
        self._declare_planning_specs(world_model.num_actions)

    @property
    def model(self) -> FramePredictor:
        """The frame predictor."""
        return self.world_model.model

    @property
    def deterministic(self) -> bool:
        return self.world_model.deterministic

    @property
    def chunk_size(self) -> int | None:
        return self.world_model.chunk_size

    @property
    def deduplicate(self) -> bool:
        return self.world_model.deduplicate

    def _set_seed(self, seed: int | None) -> None:
        """Nothing to seed: a stochastic model draws from torch's global generator."""

    def check_frame(self, frames: torch.Tensor, name: str = "pixels") -> None:
        """Refuses frames with colours outside the model's ``palette`` (if it has one).

        A palette model maps any other colour to its nearest palette colour, so a frame of
        another environment would be planned with as a misread frame of this one.
        """
        palette = getattr(self.model, "palette", None)
        if not isinstance(palette, torch.Tensor):
            return
        frames = check_frames(frames, name, shape=_FRAME)
        bad = foreign_colours(frames, palette)
        if bool(bad.any()):
            first = [int(i) for i in bad.nonzero()[0]] if bad.dim() else []
            detail = describe_foreign_colours(frames[tuple(first)], palette)
            raise ValueError(
                f"{name} holds {int(bad.sum())} frame(s) the world model cannot show (first "
                f"at batch index {first}: {detail}, the palette it was trained on). Is it a "
                "frame of another environment or setting?"
            )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = tensordict.batch_size if tensordict is not None else torch.Size([])
        given = tensordict if (kwargs.get("set_state", False) and tensordict is not None) else None
        black = torch.zeros((*shape, *_FRAME), dtype=torch.uint8, device=self.device)
        frames = {}
        for key in ("pixels", "goal_pixels"):
            value = given.get(key, None) if given is not None else None
            frames[key] = (
                black.clone()
                if value is None
                else frames_to_uint8(value, key, shape=_FRAME).expand(*shape, *_FRAME).clone()
            )
        return self._outputs(shape, frames["pixels"], frames["goal_pixels"], reward=False)

    def predict_frames(self, pixels: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Next frames for any leading shape (:meth:`FramePredictorModel.predict_frames`)."""
        return self.world_model.predict_frames(pixels, action)
