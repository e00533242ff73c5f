"""Planning envs: models of the pixel environments that a planner can step in bulk.

A model-predictive planner imagines ``N`` candidate action sequences for each of ``B``
acting envs, so it needs an environment it can step on a ``[B, N]`` batch of copies of
the current situation. The two envs here are such models. Both are stateless TorchRL
:class:`~torchrl.envs.EnvBase` subclasses with ``batch_size=()`` and
``batch_locked=False`` (any leading shape), and both produce ``pixels``, so one cost
(for example :class:`~dorp_rl.planners.PixelDistanceCost`) works on either:

- :class:`GroundTruthModelEnv` steps copies of the true configuration ``state`` with the
  environment's own dynamics and renders them: the "ground-truth model" of the paper.
- :class:`VideoModelEnv` predicts the next frame from the current frame and the action
  with a learned video prediction model.

Keys (leading shape ``*B`` arbitrary):

- ``pixels``: uint8 ``[*B, 3, 16, 16]``, the (predicted) frame;
- ``goal_pixels``: uint8 ``[*B, 3, 16, 16]``, copied unchanged from input to output
  when present, so that a goal rides along with the rollout;
- ``state``: int64 configuration (:class:`GroundTruthModelEnv` only);
- ``action``: int64 ``[*B, 1]`` under a :class:`~torchrl.data.Categorical` spec;
- ``reward`` (always 0: planners score rollouts with separate cost modules) and
  ``done`` / ``terminated`` / ``truncated`` (always ``False``: imagined rollouts run for
  the whole horizon).

Imagining candidates without stepping
    A planner steps any planning env one horizon step at a time. An env that can do
    better declares ``imagine_candidates(td, actions, next_keys)`` on its class: from
    the acting rows ``td [b]`` and the actions ``[b, N, H]`` of every candidate at every
    step, it returns ``(rollout, lazy)``: ``rollout [b, N, H]`` holding ``action`` and
    the requested ``("next", key)`` values it computes, and ``lazy``, a dict from the
    other requested keys to :class:`LazyValue` objects computed only on demand (a cost
    that knows them reads them for less, the others get them materialised); or
    ``None`` when it cannot give these keys (``next_keys=None`` asks for all of them),
    and the planner steps it. The values must be those that stepping would give.
    :meth:`GroundTruthModelEnv.imagine_candidates` is one: states from
    :meth:`~GroundTruthModelEnv.imagine`, frames as lazy :class:`ImaginedFrames`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.envs.grid_base import (
    GRID_SIZE,
    CheckedRolloutLength,
    GridWorldEnv,
    describe_foreign_colours,
    foreign_colours,
)
from dorp_rl.envs.spec import DiscreteActions
from dorp_rl.frames import check_frames, frames_to_uint8
from dorp_rl.validation import (
    MissingKeyError,
    check_action,
    check_device,
    check_int,
    check_state_layout,
)

_FRAME = (3, GRID_SIZE, GRID_SIZE)
_FRAME_BYTES = 3 * GRID_SIZE * GRID_SIZE

#: Frames per ``predict`` call of :class:`VideoModelEnv` by default. On one CPU thread the
#: video model predicted a frame in about 0.2 ms in calls of 128-2048 frames and 0.38 ms
#: in calls of 8192 (``benchmarks/predict_chunking.py``); a batched evaluation of 10
#: tasks x 1000 candidates hands it 10,000 at once.
DEFAULT_PREDICT_CHUNK = 1024


@runtime_checkable
class LazyValue(Protocol):
    """A rollout value computed only when asked for (``imagine_candidates``' ``lazy``)."""

    def materialize(self) -> torch.Tensor:
        """The value as the tensor stepping the env would have written, ``[b, N, H, ...]``."""
        ...


@runtime_checkable
class FramePredictor(Protocol):
    """What :class:`VideoModelEnv` needs from a video prediction model."""

    def predict(
        self, pixels: torch.Tensor, action: torch.Tensor, deterministic: bool = True
    ) -> torch.Tensor:
        """Next frames: uint8 ``[N, 3, 16, 16]`` and int64 ``[N, 1]`` -> uint8 ``[N, 3, 16, 16]``."""
        ...


def check_planning_action(
    action: torch.Tensor, num_actions: int, batch_shape: torch.Size | None = None
) -> torch.Tensor:
    """Validates an action tensor int ``[*B, 1]`` in ``[0, num_actions)``; returns int64 ``[*B, 1]``.

    ``batch_shape``, if given, is the expected ``B`` (see :func:`dorp_rl.validation.check_action`).
    """
    shape = None if batch_shape is None else (*batch_shape, 1)
    return check_action(action, num_actions, shape=shape)


class _PlanningEnvBase(CheckedRolloutLength, EnvBase):
    """Specs and flags shared by the planning envs (``batch_size=()``, any leading shape)."""

    _supports_set_state = True

    def __init__(self, num_actions: int, device: torch.device | str | None) -> None:
        num_actions = check_int("num_actions", num_actions, low=1)
        device = check_device(device, optional=True)
        super().__init__(device=torch.device("cpu") if device is None else device, batch_size=())
        self.__dict__["_batch_locked"] = False
        self.num_actions = num_actions
        image = Bounded(low=0, high=255, shape=_FRAME, dtype=torch.uint8, device=self.device)
        self.observation_spec = Composite(
            pixels=image, goal_pixels=image.clone(), **self._extra_observation_specs()
        )
        self.action_spec = Categorical(num_actions, shape=(1,), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())

    def _extra_observation_specs(self) -> dict:
        return {}

    def _outputs(
        self,
        shape: torch.Size,
        pixels: torch.Tensor,
        goal_pixels: torch.Tensor | None,
        *,
        reward: bool,
        **extra,
    ) -> TensorDict:
        """The output tensordict: frames, extras, all-``False`` done flags, a zero reward on steps."""
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        out = TensorDict(
            pixels=pixels,
            done=false,
            terminated=false.clone(),
            truncated=false.clone(),
            **extra,
            batch_size=shape,
            device=self.device,
        )
        if reward:
            out.set("reward", torch.zeros((*shape, 1), dtype=torch.float32, device=self.device))
        if goal_pixels is not None:
            out.set("goal_pixels", goal_pixels)
        return out


class GroundTruthModelEnv(_PlanningEnvBase):
    """The true dynamics of a :class:`~dorp_rl.envs.GridWorldEnv` as a planning model.

    Steps copies of ``state`` with ``env.transition`` and draws them with
    ``env.render_state``; all of it is vectorised, so a ``[B, N]`` batch of candidates
    costs no Python loop. The wrapped env is only used for its dynamics and renderer
    (its own batch size, step limit and goal do not matter), so the acting env itself
    can be passed.

    ``reset(td, set_state=True)`` starts from ``td["state"]`` (validated) and keeps
    ``td["goal_pixels"]`` (or renders ``td["goal_state"]``); a plain ``reset()`` samples
    a random state and goal with the wrapped env's generator (so :meth:`set_seed`
    reseeds the wrapped env). ``step`` trusts ``state`` (planners feed it from the
    acting env) and validates ``action``.

    Planners roll candidates out through :meth:`imagine_candidates` (states without a
    tensordict per step, frames left undrawn) instead of stepping. It imagines this
    class's steps: in a subclass that defines its own ``_step`` (and in that one's
    subclasses) it returns ``None``, so the planners step it, unless the subclass
    declares an ``imagine_candidates`` of its own.

    Args:
        env: the environment whose dynamics to use.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=2, seed=0)
        >>> model = GroundTruthModelEnv(env)
        >>> start = env.reset()
        >>> td = start.select("state", "pixels", "goal_pixels").expand(3, 5).clone()
        >>> td["action"] = torch.randint(0, 8, (3, 5, 1))
        >>> out = model.step(td)["next"]
        >>> out["pixels"].shape, out["state"].shape
        (torch.Size([3, 5, 3, 16, 16]), torch.Size([3, 5, 2, 2]))
    """

    #: whether :meth:`imagine_candidates` gives what stepping this class gives (see
    #: ``__init_subclass__``)
    _imagines_its_steps = True

    def __init_subclass__(cls, **kwargs) -> None:
        # What imagine computes is what this class's _step does: not in a subclass that
        # redefines _step (nor in its subclasses).
        super().__init_subclass__(**kwargs)
        if "_step" in vars(cls):
            cls._imagines_its_steps = False

    def __init__(self, env: GridWorldEnv) -> None:
        if not isinstance(env, GridWorldEnv):
            raise ValueError(
                f"env must be a dorp_rl.envs.GridWorldEnv (it provides transition and "
                f"render_state), got {type(env).__name__}."
            )
        self.__dict__["_wrapped"] = env  # set before specs are built; registered below
        super().__init__(env.num_actions, env.device)
        del self.__dict__["_wrapped"]
        self.true_env = env
        self.state_spec = Composite(state=self.observation_spec["state"].clone())

    def _extra_observation_specs(self) -> dict:
        env = self.__dict__["_wrapped"]
        low, high = env._state_bounds()
        return {
            "state": Bounded(
                low=low.expand(env.state_shape).clone(),
                high=high.expand(env.state_shape).clone(),
                dtype=torch.int64,
                device=env.device,
            )
        }

    def _set_seed(self, seed: int | None) -> None:
        self.true_env._set_seed(seed)

    def check_frame(self, frames: torch.Tensor, name: str = "pixels") -> None:
        """Refuses frames the wrapped env cannot show (:meth:`GridWorldEnv.check_frame`)."""
        self.true_env.check_frame(frames, name)

    def describe_world(self) -> str:
        """The wrapped env's world, for messages."""
        return self.true_env.describe_world()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        env = self.true_env
        shape = tensordict.batch_size if tensordict is not None else torch.Size([])
        given = tensordict if (kwargs.get("set_state", False) and tensordict is not None) else None
        state = given.get("state", None) if given is not None else None
        if state is None:
            state = env.sample_states(shape)
        else:
            state = env.check_state(state, "state").expand(*shape, *env.state_shape).clone()
        goal_pixels = given.get("goal_pixels", None) if given is not None else None
        if goal_pixels is None:
            goal_state = given.get("goal_state", None) if given is not None else None
            goal_state = (
                env.sample_goal_states(shape)
                if goal_state is None
                else env.check_state(goal_state, "goal_state").expand(*shape, *env.state_shape)
            )
            goal_pixels = env.render_state(goal_state)
        else:
            goal_pixels = (
                frames_to_uint8(goal_pixels, "goal_pixels", shape=_FRAME)
                .expand(*shape, *_FRAME)
                .clone()
            )
        return self._outputs(shape, env.render_state(state), goal_pixels, reward=False, state=state)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        env = self.true_env
        action = check_planning_action(
            tensordict.get("action"), self.num_actions, tensordict.batch_size
        ).squeeze(-1)
        state = tensordict.get("state", None)
        if state is None:
            raise KeyError(
                "GroundTruthModelEnv.step needs 'state' (the true configuration) in the "
                "tensordict; the acting env's tensordict holds it."
            )
        # Shapes only (no device synchronisation): a state of another env (e.g. another
        # number of objects) fails here instead of deep inside the dynamics.
        check_state_layout(
            state, env.state_shape, "state", owner=f"the planning model of {type(env).__name__}"
        )
        next_state = env.transition(state, action)
        return self._outputs(
            tensordict.batch_size,
            env.render_state(next_state),
            tensordict.get("goal_pixels", None),
            reward=True,
            state=next_state,
        )

    def imagine(self, state: torch.Tensor, actions: torch.Tensor) -> ImaginedFrames:
        """The states after each of ``H`` actions, their frames drawn only when needed.

        The same states as ``H`` calls of :meth:`step` from ``state`` (its
        ``("next", "state")`` at every step, whose ``("next", "pixels")`` are their
        renders), without a tensordict per step and without drawing frames that nobody
        looks at: planners use it to roll candidate sequences out.

        Args:
            state: int64 ``[*B, *state_shape]``, trusted as in ``step``; broadcast
                against the leading dimensions of ``actions``.
            actions: int ``[*L, H]`` in ``[0, num_actions)``.

        Returns:
            :class:`ImaginedFrames` over the states ``[*L, H, *state_shape]``.
        """
        env = self.true_env
        check_state_layout(
            state, env.state_shape, "state", owner=f"the planning model of {type(env).__name__}"
        )
        actions = check_planning_action(actions.unsqueeze(-1), self.num_actions).squeeze(-1)
        states = env.transitions(state, actions)
        # Frames add up from their parts only when no two blocks overlap; the dynamics
        # keep a valid state valid, so the start states decide.
        valid = not bool(env.invalid_states(state).any())
        tables = self.__dict__.setdefault("_imagined_tables", {})
        return ImaginedFrames(env, states, parts_valid=valid, tables=tables)

    #: the ``("next", key)`` entries :meth:`imagine_candidates` gives
    IMAGINED_KEYS = (("next", "pixels"), ("next", "state"))

    def imagine_candidates(
        self,
        td: TensorDictBase,
        actions: torch.Tensor,
        next_keys: list[tuple[str, ...]] | None,
    ) -> tuple[TensorDictBase, dict[tuple[str, ...], ImaginedFrames]] | None:
        """Candidates rolled out from the rows of ``td`` without stepping (planners' fast path).

        The same values as ``H`` calls of :meth:`step` (see the module docstring for the
        contract), from :meth:`imagine`: ``("next", "state")`` in the rollout,
        ``("next", "pixels")`` as lazy :class:`ImaginedFrames`, drawn only if a cost
        asks for them.

        Args:
            td: the acting rows ``[b]``, holding ``state``.
            actions: int ``[b, N, H]``, the action of every candidate at every step.
            next_keys: the ``("next", key)`` entries wanted; ``None``: all outputs.

        Returns:
            ``(rollout, lazy)``: ``rollout [b, N, H]`` with ``action`` ``[b, N, H, 1]``
            and ``("next", "state")`` if wanted, ``lazy`` ``{("next", "pixels"):
            ImaginedFrames}`` if wanted; ``None`` for other keys (``reward``, ``done``,
            ...), for ``next_keys=None``, or in a subclass that steps differently.
        """
        if not self._imagines_its_steps or next_keys is None:
            return None
        if any(key not in self.IMAGINED_KEYS for key in next_keys):
            return None
        state = td.get("state", None)
        if state is None:
            raise KeyError(
                "GroundTruthModelEnv.step needs 'state' (the true configuration) in the "
                "tensordict; the acting env's tensordict holds it."
            )
        frames = self.imagine(state.unsqueeze(1), actions)  # states [b, N, H, ...]
        rollout = TensorDict(
            {"action": actions.unsqueeze(-1)}, batch_size=actions.shape, device=td.device
        )
        if ("next", "state") in next_keys:
            rollout.set(("next", "state"), frames.states)
        lazy = {("next", "pixels"): frames} if ("next", "pixels") in next_keys else {}
        return rollout, lazy


_HASH_WEIGHTS: dict[tuple[torch.device, int], torch.Tensor] = {}
#: int8 limbs of the hash weights, ``(weights, limbs [num_bytes, 8])`` per (device, bytes)
_HASH_LIMBS: dict[tuple[torch.device, int], tuple[torch.Tensor, torch.Tensor]] = {}


def row_hashes(rows: torch.Tensor) -> torch.Tensor:
    """A 64-bit hash ``[n]`` of each row of a uint8 ``[n, ...]`` tensor (same bytes, same hash).

    The hash is ``sum_b weight_b * byte_b`` modulo 2**64 with an odd random weight per
    byte position (:func:`_hash_weights`). Odd weights make any one changed byte change
    the hash, and two different rows share a hash with probability at most about 2**-56
    (a weighted sum of byte differences, each below 2**8 in size, vanishing modulo
    2**64). A weight per 8-byte word instead would let a difference in a word's top byte
    reach only the hash's top 8 bits: frames differing there collided one time in 256.

    On the CPU the sum is one int8 matrix product (:func:`_byte_hashes`): a pass over the
    bytes, about 11 ms for 4000 rows of 3 x 76 x 76 bytes on one thread (the int64 sum
    it replaces took 0.54 s).
    """
    n = rows.shape[0]
    flat = rows.reshape(n, rows[0].numel() if n else rows.shape[1:].numel())
    weights = _hash_weights(rows.device, flat.shape[1])
    if flat.dtype == torch.uint8 and flat.device.type == "cpu" and hasattr(torch, "_int_mm"):
        return _byte_hashes(flat, weights)
    out = torch.empty(n, dtype=torch.int64, device=rows.device)
    for start in range(0, n, _HASH_CHUNK):  # bounds the int64 copy of the bytes
        chunk = flat[start : start + _HASH_CHUNK].to(torch.int64)
        out[start : start + _HASH_CHUNK] = (chunk * weights).sum(-1)
    return out


#: rows hashed at once by :func:`row_hashes` off the CPU
_HASH_CHUNK = 2048
#: bytes of rows converted at once by :func:`_byte_hashes` (stays in cache)
_HASH_CHUNK_BYTES = 1 << 22
#: columns per int8 product of :func:`_byte_hashes`: its int32 sums of ``K`` products of
#: at most 2**14 in size stay below 2**31
_HASH_BLOCK = 131064
_LIMB_SHIFTS = torch.tensor([1 << (8 * k) for k in range(8)], dtype=torch.int64)


def _hash_limbs(weights: torch.Tensor) -> torch.Tensor:
    """int8 ``[D, 8]`` signed base-256 digits ``c`` of int64 weights ``[D]``:
    ``sum_k c[:, k] * 256**k == weights`` modulo 2**64."""
    key = (weights.device, weights.shape[0])
    cached = _HASH_LIMBS.get(key)
    if cached is not None and cached[0] is weights:
        return cached[1]
    limbs, carry = [], torch.zeros_like(weights)
    for k in range(8):
        value = ((weights >> (8 * k)) & 255) + carry  # 0..256
        carry = (value >= 128).to(torch.int64)
        limbs.append(value - 256 * carry)  # -128..127
    out = torch.stack(limbs, -1).to(torch.int8)
    _HASH_LIMBS[key] = (weights, out)
    return out


def _byte_hashes(flat: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`row_hashes` of CPU uint8 rows ``[n, D]``, exactly, as int8 matrix products.

    ``sum_b w_b x_b = sum_b w_b (x_b - 128) + 128 sum_b w_b``; the bytes less 128 are int8
    (``x ^ 128``), the weights int8 digits of base 256 (:func:`_hash_limbs`), so
    ``torch._int_mm`` gives the digits' sums in int32, combined modulo 2**64.
    """
    n, num_bytes = flat.shape
    out = torch.empty(n, dtype=torch.int64)
    if n == 0 or num_bytes == 0:
        return out.fill_(0)
    limbs = _hash_limbs(weights)
    offset = 128 * weights.sum()  # modulo 2**64
    rows = max(1, _HASH_CHUNK_BYTES // num_bytes)
    buffer = torch.empty(min(rows, n), num_bytes, dtype=torch.uint8)
    for start in range(0, n, rows):
        chunk = flat[start : start + rows]
        signed = torch.bitwise_xor(chunk, 128, out=buffer[: chunk.shape[0]]).view(torch.int8)
        sums = torch.zeros(chunk.shape[0], 8, dtype=torch.int64)
        for col in range(0, num_bytes, _HASH_BLOCK):
            block = slice(col, col + _HASH_BLOCK)
            sums += torch._int_mm(signed[:, block], limbs[block])
        out[start : start + rows] = (sums * _LIMB_SHIFTS).sum(-1) + offset
    return out


def _hash_weights(device: torch.device, num_bytes: int) -> torch.Tensor:
    """The odd int64 weights ``[num_bytes]`` of :func:`row_hashes` for rows of that many bytes.

    The hash is linear in the bytes (modulo 2**64), which :class:`ImaginedFrames` uses to
    hash frames from their parts without drawing them.
    """
    key_id = (device, num_bytes)
    weights = _HASH_WEIGHTS.get(key_id)
    if weights is None:
        gen = torch.Generator().manual_seed(0x5EED)
        weights = torch.randint(-(2**62), 2**62, (num_bytes,), generator=gen) | 1
        weights = _HASH_WEIGHTS.setdefault(key_id, weights.to(device))
    return weights


def distinct_rows(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The distinct rows of a uint8 ``[n, D]`` tensor, and ``inverse`` with ``out[inverse] == rows``.

    Rows are grouped by a 64-bit hash of their bytes (one pass, no row sort); the groups
    are then checked row by row, so a hash collision never merges different rows (it
    falls back to no deduplication, ``inverse=None``). Planning repeats frames a lot
    (candidates share prefixes, blocked moves leave frames unchanged), so the models and
    encoders that run on imagined frames run on distinct ones only.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs.planning import distinct_rows
        >>> rows = torch.tensor([[1, 2], [3, 4], [1, 2]], dtype=torch.uint8)
        >>> unique, inverse = distinct_rows(rows)
        >>> unique.shape[0], bool((unique[inverse] == rows).all())
        (2, True)
    """
    n = rows.shape[0]
    if n == 0:
        return rows, torch.zeros(0, dtype=torch.long, device=rows.device)
    key = row_hashes(rows)
    unique, inverse = torch.unique(key, return_inverse=True)
    first = torch.full((unique.shape[0],), n, dtype=torch.long, device=key.device)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=key.device), reduce="amin")
    representatives = rows[first]
    if not _rows_match(rows.reshape(n, -1), representatives.reshape(first.shape[0], -1), inverse):
        return rows, None
    return representatives, inverse


def _rows_match(rows: torch.Tensor, table: torch.Tensor, index: torch.Tensor) -> bool:
    """Whether ``table[index] == rows`` (``[n, D]`` each), compared as int64 words in
    chunks that stay in cache on the CPU (a uint8 comparison there is 6x slower)."""
    if rows.device.type != "cpu" or rows.dtype != torch.uint8:
        return bool((table[index] == rows).all())
    rows = rows.contiguous()
    n, num_bytes = rows.shape
    step = max(1, _HASH_CHUNK_BYTES // max(num_bytes, 1))
    step = step - step % 8 if step >= 8 else step  # chunk starts stay word-aligned
    buffer = torch.empty(min(step, n), num_bytes, dtype=torch.uint8)
    for start in range(0, n, step):
        chunk = rows[start : start + step]
        drawn = buffer[: chunk.shape[0]]
        torch.index_select(table, 0, index[start : start + step], out=drawn)
        if not torch.equal(*_words(drawn.reshape(-1), chunk.reshape(-1))):
            return False
    return True


def _words(*flats: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """1-D uint8 tensors of one length viewed as int64 words where their offsets allow."""
    if flats[0].numel() % 8 == 0 and all(f.storage_offset() % 8 == 0 for f in flats):
        try:
            return tuple(f.view(torch.int64) for f in flats)
        except RuntimeError:
            pass
    return flats


def int64_columns(columns: torch.Tensor) -> torch.Tensor:
    """int64 ``[n, k]`` of uint8 columns ``[n, 8k]`` cut from byte rows (the inverse of
    appending ``values.view(torch.uint8)``). A fresh copy is viewed, so any row width
    works: a slice of 75-byte rows, or of a lone row, cannot be viewed as int64 itself."""
    return columns.reshape(-1).clone().view(torch.int64).reshape(columns.shape[0], -1)


def _distinct_pairs(
    pixels: torch.Tensor, action: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The distinct (frame, action) rows, and ``inverse`` with ``rows[inverse] == input``."""
    n = pixels.shape[0]
    action_bytes = action.reshape(n, 1).to(torch.int64).contiguous().view(torch.uint8)  # [n, 8]
    unique, inverse = distinct_rows(torch.cat([pixels.reshape(n, -1), action_bytes], -1))
    if inverse is None:
        return pixels, action, None
    frames = unique[:, :-8].reshape(-1, *pixels.shape[1:])
    actions = int64_columns(unique[:, -8:]).to(action.dtype)
    return frames, actions.reshape(-1, *action.shape[1:]), inverse


class ImaginedFrames:
    """Imagined states ``[*L, *state_shape]`` and their frames, drawn only when needed.

    :meth:`GroundTruthModelEnv.imagine` returns one: the states a batch of action
    sequences leads to, i.e. the ``("next", "state")`` of every step, whose
    ``("next", "pixels")`` are ``render_state(states)``; it is the lazy
    ``("next", "pixels")`` of :meth:`GroundTruthModelEnv.imagine_candidates` (a
    :class:`LazyValue`). Costs that know this class ask it for what they need instead
    of the frames themselves (see
    :meth:`dorp_rl.planners.RolloutCost.per_step_cost_lazy`):

    - :meth:`pixels` (also :meth:`materialize`): all frames, uint8 ``[*L, 3, 16, 16]``
      (drawn once, then kept);
    - :meth:`distinct`: exactly what :func:`distinct_rows` gives on the frames (with
      optional extra int64 columns), drawing only the distinct frames;
    - :meth:`squared_distances`: the exact squared L2 distance of each frame to a goal
      image, from the frame's parts, drawing no frame.

    The last two need an env whose frames are sums of non-overlapping parts
    (:meth:`~dorp_rl.envs.GridWorldEnv.frame_parts`) and valid start states (blocks that
    overlap would not add up); otherwise they fall back to drawing every frame, with the
    same results.

    Args:
        env: the environment whose renderer draws the states.
        states: int64 ``[*L, *state_shape]``.
        parts_valid: whether the states' frames are the sums of their parts (valid
            states of an env with :meth:`~dorp_rl.envs.GridWorldEnv.frame_parts`).
        tables: a dict the derived part tables are cached in (shared between calls).

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=2, batch_size=(3,), seed=0)
        >>> td = env.reset()
        >>> actions = torch.randint(0, 8, (3, 5, 4))  # 5 sequences of 4 actions per row
        >>> frames = GroundTruthModelEnv(env).imagine(td["state"].unsqueeze(1), actions)
        >>> frames.states.shape, frames.pixels().shape
        (torch.Size([3, 5, 4, 2, 2]), torch.Size([3, 5, 4, 3, 16, 16]))
        >>> goal = td["goal_pixels"].reshape(3, -1)
        >>> owner = torch.arange(3).view(3, 1, 1).expand(3, 5, 4).reshape(-1)
        >>> d2 = frames.squared_distances(goal, owner)
        >>> plain = (frames.pixels().reshape(-1, 768).long() - goal[owner].long()).square().sum(-1)
        >>> bool((d2 == plain).all())
        True
    """

    def __init__(
        self,
        env: GridWorldEnv,
        states: torch.Tensor,
        *,
        parts_valid: bool = True,
        tables: dict | None = None,
    ) -> None:
        self.env = env
        self.states = states
        self.shape = states.shape[: states.dim() - len(env.state_shape)]
        self.frame_shape = torch.Size(_FRAME)
        self._tables = {} if tables is None else tables
        self._pixels: torch.Tensor | None = None
        self._parts: torch.Tensor | None = None
        table = env.frame_part_table() if parts_valid else None
        self._has_parts = table is not None and env.frame_parts(states[:0]) is not None

    @property
    def numel(self) -> int:
        return int(self.shape.numel())

    def pixels(self) -> torch.Tensor:
        """uint8 ``[*L, 3, 16, 16]``: every frame (``env.render_state(states)``)."""
        if self._pixels is None:
            self._pixels = self.env.render_state(self.states)
        return self._pixels

    def materialize(self) -> torch.Tensor:
        """:meth:`pixels`: the frames stepping the env would have written (:class:`LazyValue`)."""
        return self.pixels()

    def _flat_states(self) -> torch.Tensor:
        return self.states.reshape(self.numel, *self.env.state_shape)

    def _flat_parts(self) -> torch.Tensor:
        if self._parts is None:
            self._parts = self.env.frame_parts(self._flat_states())
        return self._parts

    def _table(self, name: str) -> torch.Tensor:
        """Derived part tables, computed once per env and device."""
        key = (name, self.states.device)
        if key not in self._tables:
            parts = self.env.frame_part_table().to(self.states.device).reshape(-1, _FRAME_BYTES)
            if name == "float64":
                value = parts.to(torch.float64)
            elif name == "norms":
                value = parts.to(torch.int64).square().sum(-1)
            else:  # part hashes for rows of `name` bytes
                weights = _hash_weights(self.states.device, name)[: parts.shape[1]]
                value = (parts.to(torch.int64) * weights).sum(-1)
            self._tables[key] = value
        return self._tables[key]

    def distinct(
        self, extra: torch.Tensor | None = None, *, draw: bool = True
    ) -> tuple[
        torch.Tensor | Callable[[torch.Tensor | None], torch.Tensor],
        torch.Tensor | None,
        torch.Tensor | None,
        torch.Tensor | None,
    ]:
        """:func:`distinct_rows` of the frames (joined with ``extra`` columns), drawing distinct ones.

        Args:
            extra: int64 ``[n, e]`` joined to each flat frame (``n = prod(L)``), as its
                bytes; ``None`` for the frames alone.
            draw: ``False`` returns, instead of the distinct frames, a function drawing
                those of given indices (``None``: all), when the rows were found without
                drawing them (a cache keyed by ``keys`` may need only a few).

        Returns:
            ``(frames, extra, inverse, keys)``: the rows ``distinct_rows`` returns on
            ``cat(frames.reshape(n, -1), extra.view(uint8))``, split into uint8 frames
            ``[m, 3, 16, 16]`` (or the function drawing them) and int64 extras ``[m, e]``
            (``None`` without ``extra``); its ``inverse`` (``None``: no deduplication, all
            ``n`` rows returned); and :func:`row_hashes` of the returned rows (``None``
            when not known).
        """
        n = self.numel
        if not self._has_parts:
            return self._distinct_drawn(extra)
        parts = self._flat_parts()
        num_bytes = _FRAME_BYTES + (0 if extra is None else 8 * extra.shape[1])
        key = self._table(num_bytes)[parts].sum(-1)  # the hash is linear in the bytes
        if extra is not None:
            extra_bytes = extra.contiguous().view(torch.uint8).to(torch.int64)
            weights = _hash_weights(key.device, num_bytes)[_FRAME_BYTES:]
            key = key + (extra_bytes * weights).sum(-1)
        unique, inverse = torch.unique(key, return_inverse=True)
        first = torch.full((unique.shape[0],), n, dtype=torch.long, device=key.device)
        first.scatter_reduce_(0, inverse, torch.arange(n, device=key.device), reduce="amin")
        # distinct_rows checks that every row equals its group's first row: equal parts
        # (and extras) mean equal bytes; rows that differ there are compared as frames.
        owner = first[inverse]
        differ = (parts[owner] != parts).any(-1)
        if extra is not None:
            differ |= (extra[owner] != extra).any(-1)
        if bool(differ.any()):
            rows = differ.nonzero().squeeze(-1)
            states = self._flat_states()
            same = torch.equal(
                self.env.render_state(states[rows]), self.env.render_state(states[owner[rows]])
            )
            if extra is not None:
                same = same and torch.equal(extra[rows], extra[owner[rows]])
            if not same:  # a hash collision: distinct_rows gives up deduplication
                return self._distinct_drawn(extra)
        states = self._flat_states()[first]

        def draw_frames(index: torch.Tensor | None = None) -> torch.Tensor:
            return self.env.render_state(states if index is None else states[index])

        frames = draw_frames() if draw else draw_frames
        return frames, None if extra is None else extra[first], inverse, unique

    def _distinct_drawn(self, extra: torch.Tensor | None):
        """:meth:`distinct` by drawing every frame and calling :func:`distinct_rows`."""
        n = self.numel
        flat = self.pixels().reshape(n, *_FRAME)
        if extra is None:
            rows, inverse = distinct_rows(flat)
            return rows, None, inverse, None
        rows, inverse = distinct_rows(
            torch.cat([flat.reshape(n, -1), extra.contiguous().view(torch.uint8)], -1)
        )
        frames = rows[:, :_FRAME_BYTES].reshape(-1, *_FRAME)
        return frames, int64_columns(rows[:, _FRAME_BYTES:]), inverse, None

    def squared_distances(self, goals: torch.Tensor, owner: torch.Tensor) -> torch.Tensor | None:
        """Exact squared L2 distances int64 ``[n]`` of the frames to their goal images.

        Frame ``i`` (flat index over ``L``) is compared with ``goals[owner[i]]``, in
        integer arithmetic on the 0..255 values. Computed from the frames' parts:
        ``|f - g|^2 = |g|^2 + sum_p (|part_p|^2 - 2 <part_p, g>)`` (parts do not overlap).

        Args:
            goals: uint8 ``[G, 768]`` goal frames (flat).
            owner: int64 ``[n]``, the goal of each frame.

        Returns:
            int64 ``[n]``, or ``None`` when the frames are not sums of parts (draw them).
        """
        if not self._has_parts or goals.dtype != torch.uint8:
            return None
        table = self._table("float64")  # [T, 768]
        g = goals.reshape(goals.shape[0], -1).to(table.device, torch.float64)
        # Integers below 2**53 throughout (768 * 255**2 at most): the products are exact.
        dots = (table @ g.T).to(torch.int64)  # [T, G]
        per_part = (self._table("norms").unsqueeze(-1) - 2 * dots).T.contiguous()  # [G, T]
        goal_norms = g.square().sum(-1).to(torch.int64)  # [G]
        parts = self._flat_parts()
        index = owner.unsqueeze(-1) * per_part.shape[1] + parts
        return goal_norms[owner] + per_part.reshape(-1)[index].sum(-1)


class VideoModelEnv(_PlanningEnvBase):
    """A video prediction model as a planning env: next ``pixels`` from ``pixels`` and ``action``.

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
        if device is None and isinstance(model, torch.nn.Module):
            param = next(iter(model.parameters()), None)
            device = param.device if param is not None else None
        super().__init__(num_actions, device)
        self.model = model
        self.deterministic = bool(deterministic)
        self.chunk_size = None if chunk_size is None else int(chunk_size)
        if deduplicate and not self.deterministic:
            raise ValueError(
                "deduplicate=True needs deterministic=True: a stochastic model gives "
                "different frames for equal inputs."
            )
        self.deduplicate = self.deterministic if deduplicate is None else bool(deduplicate)

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

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        pixels = tensordict.get("pixels", None)
        if pixels is None:
            raise KeyError("VideoModelEnv.step needs 'pixels' (the current frame).")
        action = check_planning_action(
            tensordict.get("action"), self.num_actions, tensordict.batch_size
        )
        next_pixels = self.predict_frames(pixels, action)
        return self._outputs(
            tensordict.batch_size, next_pixels, tensordict.get("goal_pixels", None), reward=True
        )


class StatelessEnvModel(CheckedRolloutLength, EnvBase):
    """The true dynamics of any stateless TorchRL env as a planning model (any leading shape).

    A stateless env reads everything it needs from the tensordict it steps (torchrl's
    convention, e.g. ``PendulumEnv``): its state entries, here ``state``. This model
    hands the env's ``_step`` every entry of the env's observation (and state) spec that
    the planning tensordict holds, plus the action, so an env reading e.g. ``step_count``
    steps here as it does when acting; a missing ``goal_state`` is filled with ``state``
    and a missing ``goal_pixels`` with zeros (a goal is not needed to imagine a step) and
    left out of the output. A ``[*B]`` batch of candidates is flattened to rows: an env
    of any shape takes them at once; an env whose batch is fixed at ``(n,)`` takes them
    in chunks of ``n``, or at once if a probe on the first step finds that its ``_step``
    gives exactly the chunks' results on the whole batch. ``goal_pixels`` ride along
    unchanged; the done flags are always ``False`` and the reward 0 (imagined rollouts run
    the whole horizon and are scored by cost modules).

    Args:
        env: the env whose dynamics to use; it must step from a tensordict holding
            ``state`` and an action (``_supports_set_state`` and a ``state`` entry).

    Raises:
        MissingKeyError: (a ``ValueError`` and a ``KeyError``) from ``step`` when the
            env's ``_step`` looks up an entry the planning tensordict lacks.

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.envs.planning import StatelessEnvModel
        >>> model = StatelessEnvModel(ObjectRearrangementEnv(num_objects=1, batch_size=(4,)))
        >>> td = model.reset().expand(3, 5).clone()
        >>> td["action"] = model.action_spec.rand((3, 5))
        >>> model.step(td)["next", "pixels"].shape
        torch.Size([3, 5, 3, 16, 16])
    """

    _supports_set_state = True

    def __init__(self, env: EnvBase) -> None:
        if not isinstance(env, EnvBase):
            raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
        if "state" not in env.observation_spec.keys() or not getattr(
            env, "_supports_set_state", False
        ):
            raise ValueError(
                f"{type(env).__name__} cannot serve as its own true dynamics: a planning model "
                "steps copies of a situation, so the env must write a 'state' entry, step from "
                "it (stateless) and take it back on reset(td, set_state=True) "
                "(_supports_set_state = True)."
            )
        super().__init__(device=env.device, batch_size=())
        self.__dict__["_batch_locked"] = False
        self.true_env = env
        batch = len(env.batch_size)
        self.rows = int(env.batch_size.numel()) if env.batch_locked and batch else None
        #: whether the env's ``_step`` takes a whole flat batch (fixed batch only; ``None``:
        #: not probed yet)
        self.whole_batch: bool | None = None

        def unbatched(spec: Composite, keys) -> Composite:
            return Composite({k: spec[k][(0,) * batch].clone() for k in keys})

        self.observation_spec = unbatched(env.observation_spec, env.observation_spec.keys())
        observed = set(self.observation_spec.keys())
        extra = [k for k in env.state_spec.keys() if k not in observed]
        if extra:  # entries the env reads besides its observations (torchrl's "params")
            self.state_spec = unbatched(env.state_spec, extra)
        #: the entries handed to the env's ``_step`` when the tensordict holds them
        self._step_keys = [*self.observation_spec.keys(), *extra]
        # Planners draw indices; a one-hot env gets them in its own layout.
        self.actions = DiscreteActions.of(env)
        self.action_spec = Categorical(
            self.actions.num_actions, shape=(1,), dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(1,), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())

    def _set_seed(self, seed: int | None) -> None:
        self.true_env.set_seed(seed)

    def _by_rows(self, rows: TensorDictBase, call) -> TensorDictBase:
        """``call`` on flat ``rows`` ``[n]``: at once for an env of any shape, else in
        chunks of the env's batch (the last one padded with repeats); ``[n]`` back."""
        if self.rows is None:
            return call(rows)
        n, size = rows.shape[0], self.rows
        pad = (-n) % size
        if pad:
            rows = torch.cat([rows, rows[:1].expand(pad).clone()], 0)
        batch = self.true_env.batch_size
        outs = [call(rows[i : i + size].reshape(batch)) for i in range(0, rows.shape[0], size)]
        return torch.cat([o.reshape(-1) for o in outs], 0)[:n]

    def _step_rows(self, rows: TensorDictBase) -> TensorDictBase:
        """The env's ``_step`` on flat ``rows`` ``[n]``: by chunks of a fixed batch until a
        probe (the first batch of another size than the env's) finds the whole batch at
        once gives exactly the same outputs; ``[n]`` back."""
        step = self.true_env._step
        n = rows.shape[0]
        if self.rows is None or n == self.rows:
            return self._by_rows(rows, step)
        if self.whole_batch:
            return step(rows)
        out = self._by_rows(rows, step)
        if self.whole_batch is None:
            self.whole_batch = _same_outputs(out, _try_call(step, rows))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        env = self.true_env
        keys = self._step_keys
        if tensordict is None or not kwargs.get("set_state", False):
            td = env.reset()
            return td.reshape(-1)[0].select(*keys, strict=False).clone()
        out = self._by_rows(
            tensordict.reshape(-1), lambda rows: env.reset(rows.clone(), set_state=True)
        )
        return out.select(*keys, strict=False).reshape(tensordict.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        rows = tensordict.select(*self._step_keys, "action", strict=False).reshape(-1)
        rows.set("action", self.actions.from_index(rows.get("action")))
        given = sorted(str(k) for k in rows.keys())
        filled = []  # a goal is not needed to imagine a step
        if "goal_state" not in rows.keys():
            rows.set("goal_state", rows.get("state").clone())
            filled.append("goal_state")
        if "goal_pixels" in self.observation_spec.keys() and "goal_pixels" not in rows.keys():
            rows.set("goal_pixels", self.observation_spec["goal_pixels"].zero(rows.batch_size))
            filled.append("goal_pixels")
        try:
            out = self._step_rows(rows)
        except KeyError as err:
            raise self._missing_entry(err, given) from err
        out = out.select(*self._step_keys, strict=False).exclude(*filled).reshape(shape)
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        out.update(
            {
                "reward": torch.zeros((*shape, 1), dtype=torch.float32, device=self.device),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            }
        )
        if "goal_pixels" in tensordict.keys():
            out.set("goal_pixels", tensordict.get("goal_pixels"))
        return out

    def _missing_entry(self, err: KeyError, given: list[str]) -> MissingKeyError:
        """The error naming the entry the env's ``_step`` looked up and did not find
        (``given``: the entries the planning tensordict held)."""
        name = type(self.true_env).__name__
        text = str(err.args[0]) if err.args else ""
        found = re.search(r'key "(.+?)" not found', text)
        key = found.group(1) if found else (err.args[0] if err.args else "?")
        specs = [self.observation_spec, self.state_spec]
        declared = {k for spec in specs for k in spec.keys(True)}
        declared |= {k[-1] for k in declared if isinstance(k, tuple)}  # tensordict names leaves
        if key in declared:
            why = (
                f"{key!r} is in {name}'s observation spec, and the planner hands the model "
                "the entries the acting tensordict holds: that tensordict lacks it (the env's "
                "reset writes it; keep it in what the policy is given)."
            )
        else:
            why = (
                f"{key!r} is not in {name}'s observation spec: the planning tensordict "
                "carries what the env declares there (as its reset writes it), so declare it."
            )
        return MissingKeyError(
            f"{name}._step looked up {key!r}, missing from the planning tensordict that "
            f"StatelessEnvModel (dorp_rl.envs.planning, the planning model of the env's true "
            f"dynamics) stepped it on, which holds {given}. {why}"
        )


def _try_call(call, rows: TensorDictBase) -> TensorDictBase | None:
    """``call(rows)``, or ``None`` if it raises."""
    try:
        return call(rows)
    except Exception:  # noqa: BLE001 (any failure means: step in chunks)
        return None


def _same_outputs(expected: TensorDictBase, got: TensorDictBase | None) -> bool:
    """Whether ``got`` holds exactly ``expected``'s entries (keys, shapes, dtypes, values)."""
    if not isinstance(got, TensorDictBase) or got.batch_size != expected.batch_size:
        return False
    keys = set(expected.keys(True, True))
    if set(got.keys(True, True)) != keys:
        return False
    for key in keys:
        a, b = expected.get(key), got.get(key)
        if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
            if a.dtype != b.dtype or not torch.equal(a, b):
                return False
            continue
        try:  # non-tensor entries
            if not bool(a == b):
                return False
        except Exception:  # noqa: BLE001 (no comparison: no proof of sameness)
            return False
    return True
