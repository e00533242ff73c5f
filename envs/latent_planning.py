"""A latent world model as a planning env, through torchrl's ``WorldModelEnv``.

:class:`LatentModelEnv` drives a latent world model (:class:`~dorp_rl.modules.LatentWorldModel`,
or any object with its methods) with torchrl's
:class:`~torchrl.envs.model_based.WorldModelEnv`: the frame is encoded once, each step
advances the latent and writes the codes read off it (``code``), and frames are decoded
only when asked for (``decode=True``). So ``env.rollout``, torchrl's own planners and
this library's planners all step it the same way.
"""

from __future__ import annotations

import contextlib
import functools
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.model_based import WorldModelEnv as TorchRLWorldModelEnv

from dorp_rl.frames import frames_to_uint8
from dorp_rl.integrity import state_digest
from dorp_rl.validation import check_device

__all__ = ["LatentModelEnv", "planning_dtype"]

#: what ``compute_dtype`` accepts
COMPUTE_DTYPES = ("auto", "float32", "bfloat16")


@functools.cache
def _cpu_runs_bfloat16() -> bool:
    """Whether this CPU has bfloat16 instructions (AVX512-BF16 or AMX-BF16; read from
    ``/proc/cpuinfo``, so False where that file is missing). Without them oneDNN
    emulates bfloat16, slower than float32."""
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return ("avx512_bf16" in flags or "amx_bf16" in flags) and bool(
        torch.ops.mkldnn._is_mkldnn_bf16_supported()
    )


def planning_dtype(compute_dtype: str, device: torch.device) -> torch.dtype:
    """The dtype a latent model imagines in on ``device``: ``"float32"``, ``"bfloat16"``,
    or ``"auto"``: bfloat16 where the hardware runs it natively (a CUDA device that
    supports it, a CPU with bfloat16 instructions), else float32.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import planning_dtype
        >>> planning_dtype("float32", torch.device("cpu"))
        torch.float32
    """
    if compute_dtype not in COMPUTE_DTYPES:
        raise ValueError(f"compute_dtype must be one of {COMPUTE_DTYPES}, got {compute_dtype!r}.")
    if compute_dtype != "auto":
        return getattr(torch, compute_dtype)
    if device.type == "cuda":
        native = torch.cuda.is_bf16_supported()
    else:
        native = device.type == "cpu" and _cpu_runs_bfloat16()
    return torch.bfloat16 if native else torch.float32


class LatentModelEnv(TorchRLWorldModelEnv):
    """Plans in a latent world model's latent space: ``pixels`` in, ``code`` per step out.

    It steps the model's torchrl ``WorldModel`` (its ``step_module``: dynamics, code
    head, reward and, with ``decode``, the decoder), and is a subclass of torchrl's
    ``WorldModelEnv`` that differs in three ways, each for the planners: a step (or reset)
    from a tensordict without ``latent`` first encodes its ``pixels`` (a planner hands a
    planning env the acting env's tensordict, which holds frames), every later step
    advancing the latent alone; its specs come from the model (any ``[C, H, W]`` frames,
    ``num_actions`` indices, ``code`` of its code sizes), not from a reference env; and
    it is stateless with any leading shape (``batch_size=()``, not batch-locked, outputs
    shaped as the tensordict), where torchrl's shapes them by the env's batch size.

    Writes at each step ``latent`` float ``[D]``, ``code`` int64 ``[K]`` (the code head's
    most likely codes), a zero ``reward``, ``done`` flags all ``False``, and with
    ``decode`` the decoded ``pixels`` uint8 ``[C, H, W]``; ``goal_pixels`` are carried.

    Args:
        model: the latent world model (``encode``, ``step``, ``codes``, ``decode_uint8``,
            ``as_world_model``, ``num_actions``, ``code_sizes``, ``frame_shape``).
        decode: decode a frame at every step (for costs that read ``("next", "pixels")``).
        device: where tensors live (default: the model's parameters' device).
        compute_dtype: what the steps, code head and decoder compute in: ``"float32"``,
            ``"bfloat16"`` (through :func:`torch.autocast`; the start frame is still
            encoded, and latents and frames written, in float32), or ``"auto"``
            (:func:`planning_dtype`: bfloat16 where the hardware runs it natively).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.envs import LatentModelEnv
        >>> from dorp_rl.modules import LatentModelConfig, LatentWorldModel
        >>> model = LatentWorldModel(4, LatentModelConfig(frame_shape=(3, 24, 32), code_sizes=(8, 8)))
        >>> env = LatentModelEnv(model)
        >>> td = TensorDict(pixels=torch.zeros(2, 5, 3, 24, 32, dtype=torch.uint8),
        ...                 action=torch.zeros(2, 5, 1, dtype=torch.int64), batch_size=(2, 5))
        >>> out = env.step(td)
        >>> out["next", "code"].shape, out["next", "latent"].shape
        (torch.Size([2, 5, 2]), torch.Size([2, 5, 128]))
    """

    _supports_set_state = True

    def __init__(
        self, model: Any, *, decode: bool = False, device: Any = None, compute_dtype: str = "auto"
    ) -> None:
        for name in ("encode", "step", "codes", "as_world_model", "num_actions", "code_sizes"):
            if not hasattr(model, name):
                raise ValueError(
                    f"model must be a latent world model (LatentWorldModel); "
                    f"{type(model).__name__} has no {name!r}."
                )
        if device is None and isinstance(model, torch.nn.Module):
            param = next(iter(model.parameters()), None)
            device = param.device if param is not None else None
        device = torch.device("cpu") if device is None else check_device(device)
        frame = tuple(model.frame_shape)
        image = Bounded(low=0, high=255, shape=frame, dtype=torch.uint8, device=device)
        latent_dim = int(model.latent_width)
        observation = Composite(
            pixels=image,
            goal_pixels=image.clone(),
            latent=Unbounded(shape=(latent_dim,), dtype=torch.float32, device=device),
            code=Unbounded(shape=(len(model.code_sizes),), dtype=torch.int64, device=device),
        )
        world_model = model.as_world_model(decode=decode)
        # torchrl's WorldModelEnv.__init__ copies its specs from a batched reference env
        # (and cannot expand them to batch_size=()); the model has its own, so the base
        # is set up directly and the specs are the model's.
        ModelBasedEnvBase.__init__(
            self,
            world_model.step_module,
            device=device,
            batch_size=torch.Size([]),
            allow_done_after_reset=True,
        )
        self._world_model = world_model
        self.latent_key = "latent"
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.action_spec = Categorical(int(model.num_actions), shape=(1,), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())
        self.observation_spec = observation
        self.model = model
        self.decode = bool(decode)
        self.num_actions = int(model.num_actions)
        self.compute_dtype = compute_dtype
        #: the dtype the steps run in (``compute_dtype`` resolved on ``device``)
        self.step_dtype = planning_dtype(compute_dtype, device)

    def _computing(self) -> contextlib.AbstractContextManager:
        """Autocast to :attr:`step_dtype` (nothing for float32)."""
        if self.step_dtype == torch.float32:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.step_dtype)

    def _set_seed(self, seed: int | None) -> None:
        """Nothing to seed: the model is deterministic."""

    def check_frame(self, frames: torch.Tensor, name: str = "pixels") -> None:
        """Frames must have the model's ``[C, H, W]``."""
        frames_to_uint8(frames, name, shape=tuple(self.model.frame_shape))

    def _with_latent(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``tensordict`` with ``latent`` (its ``pixels`` encoded when it has none)."""
        if self.latent_key in tensordict.keys():
            return tensordict
        pixels = tensordict.get("pixels", None)
        if pixels is None:
            raise KeyError(
                "LatentModelEnv needs 'latent' or 'pixels' (the frame to start from) in the "
                f"tensordict; it holds {sorted(str(k) for k in tensordict.keys())}."
            )
        pixels = frames_to_uint8(pixels, "pixels", shape=tuple(self.model.frame_shape))
        out = tensordict.copy()
        with torch.no_grad():
            out.set(self.latent_key, self.model.encode(pixels))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is None:
            raise KeyError("LatentModelEnv.reset needs a tensordict with 'pixels' or 'latent'.")
        tensordict = self._with_latent(tensordict)
        shape = tensordict.batch_size
        latent = tensordict.get(self.latent_key)
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        with torch.no_grad():
            code = self.model.codes(latent)
        out = TensorDict(
            {
                self.latent_key: latent,
                "code": code,
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=shape,
            device=self.device,
        )
        for key in ("pixels", "goal_pixels"):
            value = tensordict.get(key, None)
            if value is not None:
                out.set(key, value)
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self._with_latent(tensordict)
        shape = tensordict.batch_size
        with torch.no_grad(), self._computing():
            nxt = self.world_model(tensordict.copy()).get("next")
        # torchrl's WorldModelEnv._step builds its output with the env's batch_size; the
        # planners step [b, N] candidates through a batch_size=() env, so it is built here
        # with the tensordict's shape.
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        out = TensorDict(
            {
                self.latent_key: nxt.get(self.latent_key).float(),
                "code": nxt.get("code"),
                "reward": nxt.get("reward"),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=shape,
            device=self.device,
        )
        if self.decode:
            out.set("pixels", nxt.get("pixels"))
        goal = tensordict.get("goal_pixels", None)
        if goal is not None:
            out.set("goal_pixels", goal)
        return out

    @property
    def latent_model(self) -> Any:
        """The model whose latents it writes under ``latent``: goal costs compare them with
        ``latent_model.encode`` of the goal image (:class:`~dorp_rl.planners.LatentGoalCost`)."""
        return self.model

    def predicts_codes_of(self, encoder: torch.nn.Module) -> bool:
        """Whether ``code`` may stand for ``encoder``'s codes of the imagined frames: False
        when the model records the digest of the encoder it learned
        (``config.encoder_digest``) and ``encoder``'s weights differ (an ablation's
        encoder, say), so that costs encode decoded frames instead; True otherwise."""
        learned = getattr(getattr(self.model, "config", None), "encoder_digest", None)
        return learned is None or learned == state_digest(encoder)

    def without_frames(self) -> LatentModelEnv:
        """The same model as a planning env that decodes no frames (codes only)."""
        return LatentModelEnv(
            self.model, decode=False, device=self.device, compute_dtype=self.compute_dtype
        )

    #: what :meth:`imagine_candidates` can give
    IMAGINED_KEYS = (("next", "latent"), ("next", "code"), ("next", "pixels"))

    def imagine_candidates(
        self, td: TensorDictBase, actions: torch.Tensor, next_keys: list | None
    ) -> tuple[TensorDictBase, dict] | None:
        """Candidates ``[b, N, H]`` rolled out in latent space without a tensordict per
        step (the planners' fast path; the same values as ``H`` calls of :meth:`step`):
        the rows' frames are encoded once, the latents stepped in one batch, the codes
        read off all of them at once and frames decoded only if wanted (and ``decode``).
        ``None`` for keys it does not imagine (the planner then steps it)."""
        if next_keys is None or any(key not in self.IMAGINED_KEYS for key in next_keys):
            return None
        if ("next", "pixels") in next_keys and not self.decode:
            return None  # stepped, so that the missing frames are named
        start = self._with_latent(td).get(self.latent_key)
        with torch.no_grad(), self._computing():
            latent = start.unsqueeze(-2).expand(*actions.shape[:-1], start.shape[-1])
            latents = self.model.imagine(latent, actions)  # [b, N, H, D]
            rollout = TensorDict(
                {"action": actions.unsqueeze(-1)}, batch_size=actions.shape, device=td.device
            )
            if ("next", "latent") in next_keys:
                rollout.set(("next", "latent"), latents.float())
            if ("next", "code") in next_keys:
                rollout.set(("next", "code"), self.model.codes(latents))
            if ("next", "pixels") in next_keys:
                rollout.set(("next", "pixels"), self.model.decode_uint8(latents))
        return rollout, {}
