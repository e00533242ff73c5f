"""Shared machinery of the paper's 16x16 pixel environments.

:class:`GridWorldEnv` is a stateless, batched TorchRL :class:`~torchrl.envs.EnvBase`:
every quantity that defines an episode (configuration, goal, step counter) lives in the
tensordict, and every operation is vectorised over the leading batch dimensions.
Subclasses only describe their world: how to sample valid configurations, how one
action changes a configuration, how a configuration is drawn, and how far apart two
configurations are.
"""

from __future__ import annotations

import copy
import weakref
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.frames import check_frames
from dorp_rl.validation import (
    BatchShapeError,
    MissingKeyError,
    check_action,
    check_batch_size,
    check_bool,
    check_device,
    check_int,
    check_seed,
    check_state_layout,
)

GRID_SIZE = 16

# Directions of a unit move, indexed as in the paper's action encoding:
# 0 up (row - 1), 1 down (row + 1), 2 left (column - 1), 3 right (column + 1).
DIRECTIONS = torch.tensor([[-1, 0], [1, 0], [0, -1], [0, 1]], dtype=torch.int64)


def paint_layers(masks: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """Paints boolean layers onto a black canvas; later layers cover earlier ones.

    This is the one renderer of the package: every environment describes its frame as
    a stack of masks with one colour each.

    Args:
        masks: bool ``[*B, L, H, W]``, one mask per layer.
        colours: uint8 ``[L, 3]``, the RGB colour of each layer.

    Returns:
        uint8 ``[*B, 3, H, W]`` image.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import paint_layers
        >>> masks = torch.zeros(2, 4, 4, dtype=torch.bool)
        >>> masks[0, :2] = True  # layer 0: the top two rows
        >>> masks[1, :, 0] = True  # layer 1: the left column, painted over layer 0
        >>> image = paint_layers(masks, torch.tensor([[255, 0, 0], [0, 0, 255]], dtype=torch.uint8))
        >>> image.shape, image[:, 0, 0].tolist(), image[:, 0, 1].tolist(), image[:, 3, 3].tolist()
        (torch.Size([3, 4, 4]), [0, 0, 255], [255, 0, 0], [0, 0, 0])
    """
    num_layers = masks.shape[-3]
    # Index of the top-most layer covering each pixel (0 = background).
    depth = torch.arange(1, num_layers + 1, device=masks.device).view(num_layers, 1, 1)
    top = (masks.to(torch.int64) * depth).amax(dim=-3)  # [*B, H, W]
    palette = torch.cat(
        [
            torch.zeros(1, 3, dtype=torch.uint8, device=masks.device),
            colours.to(masks.device, torch.uint8),
        ]
    )  # [L + 1, 3]
    image = palette[top]  # [*B, H, W, 3]
    return image.movedim(-1, -3).contiguous()


def colour_codes(frames: torch.Tensor) -> torch.Tensor:
    """Each pixel's colour as one integer ``r << 16 | g << 8 | b``: uint8 ``[*B, 3, H, W]`` -> int32 ``[*B, H, W]``."""
    c = frames.to(torch.int32)
    return (c[..., 0, :, :] << 16) | (c[..., 1, :, :] << 8) | c[..., 2, :, :]


def foreign_colours(frames: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """bool ``[*B]``: which frames hold a colour outside ``colours`` (uint8 ``[K, 3]``)."""
    allowed = colour_codes(colours.to(frames.device).t().reshape(3, -1, 1)).reshape(-1)
    codes = colour_codes(frames).flatten(-2)  # [*B, H * W]
    return ~torch.isin(codes, allowed).all(-1)


def describe_foreign_colours(frame: torch.Tensor, colours: torch.Tensor) -> str:
    """The colours of one frame ``[3, H, W]`` outside ``colours``, and those, for a message."""
    found = frame.reshape(3, -1).t().unique(dim=0)
    allowed = {tuple(c) for c in colours.tolist()}
    extra = [c for c in found.tolist() if tuple(c) not in allowed]
    return f"colours {extra} are not among its colours {colours.tolist()}"


class CheckedRolloutLength:
    """Mixin of the dorp-rl envs: ``rollout(max_steps)`` refuses ``max_steps < 1`` by name
    (torchrl's own ``rollout(0)`` fails with ``list_of_tensordicts cannot be empty``)."""

    def rollout(self, max_steps: int, *args, **kwargs) -> TensorDictBase:
        """:meth:`torchrl.envs.EnvBase.rollout`, after checking ``max_steps`` (an integer >= 1)."""
        max_steps = check_int("max_steps", max_steps, low=1)
        return super().rollout(max_steps, *args, **kwargs)


class _EmittedTensors:
    """The last few state tensors an env produced, with their version counters.

    ``step`` checks a state only when it is not one of these, unchanged: a state the env
    produced itself is valid by construction, so a rollout checks nothing per step (no
    device synchronisation), while a state written into the tensordict by hand (or
    changed in place) is checked like a state given to ``reset``. Not copied or pickled:
    a copied env starts trusting nothing.
    """

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self.entries: list[tuple[weakref.ref, int]] = []

    def add(self, *tensors: torch.Tensor) -> None:
        self.entries = [(ref, v) for ref, v in self.entries if ref() is not None]
        self.entries += [(weakref.ref(t), t._version) for t in tensors]
        self.entries = self.entries[-self.size :]

    def __contains__(self, tensor: torch.Tensor) -> bool:
        return any(ref() is tensor and tensor._version == v for ref, v in self.entries)

    def __deepcopy__(self, memo: dict) -> _EmittedTensors:
        return _EmittedTensors(self.size)

    def __reduce__(self):
        return (_EmittedTensors, (self.size,))


class GridWorldEnv(CheckedRolloutLength, EnvBase):
    """Base class of the 16x16 pixel environments (stateless, batched).

    Keys produced by ``reset`` and ``step``:

    - ``pixels`` / ``goal_pixels``: uint8 ``[*B, 3, 16, 16]`` (black background);
    - ``state`` / ``goal_state``: int64 ground-truth configuration (shape per env);
    - ``step_count``: int64 ``[*B, 1]``, steps taken in the episode;
    - ``success``: bool ``[*B, 1]``, ``state == goal_state``;
    - ``reward``: 1.0 when the goal is reached, else 0.0;
    - ``terminated`` on success, ``truncated`` at ``max_steps``, ``done`` either.

    The action is int64 ``[*B, 1]`` under a :class:`~torchrl.data.Categorical` spec.

    ``reset()`` samples a random valid start and goal. ``reset(td, set_state=True)``
    starts from the ``state`` and/or ``goal_state`` found in ``td`` (missing ones are
    sampled). With ``batch_size=()`` and ``batch_locked=False`` the env accepts any
    leading shape, which is how it serves as a planning model.

    Args:
        max_steps: episode length before ``truncated`` is set.
        batch_size: number of independent copies (any shape).
        device: where tensors live.
        seed: seeds the env's own generator (see :meth:`set_seed`).
        batch_locked: if ``False`` (only with ``batch_size=()``), any leading shape works.
        terminate_on_success: set ``terminated`` when the goal is reached. Play-data
            collection turns it off so that random walks are not cut by random goals.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
        >>> task = TensorDict(
        ...     state=torch.tensor([[[0, 0]]]), goal_state=torch.tensor([[[1, 0]]]), batch_size=(1,)
        ... )
        >>> td = env.reset(task, set_state=True)  # start and goal as given
        >>> td["action"] = torch.tensor([[1]])  # block 0 one cell down
        >>> out = env.step(td)["next"]
        >>> out["state"].tolist(), out["success"].tolist(), out["reward"].tolist()
        ([[[1, 0]]], [[True]], [[1.0]])
    """

    _supports_set_state = True
    grid_size = GRID_SIZE
    #: Length of one play-data trajectory (the paper resets rearrangement after every step).
    PLAY_TRAJECTORY_LENGTH: int = 1

    def __init__(
        self,
        *,
        max_steps: int,
        batch_size: Sequence[int] | torch.Size = (),
        device: torch.device | str | None = None,
        seed: int | None = None,
        batch_locked: bool = True,
        terminate_on_success: bool = True,
    ) -> None:
        batch_size = check_batch_size(batch_size)
        batch_locked = check_bool("batch_locked", batch_locked)
        if not batch_locked and batch_size != torch.Size([]):
            raise ValueError(
                f"batch_locked=False needs batch_size=(), got batch_size={tuple(batch_size)}."
            )
        max_steps = check_int("max_steps", max_steps, low=1)
        seed = check_seed(seed, optional=True)
        terminate_on_success = check_bool("terminate_on_success", terminate_on_success)
        device = check_device(device, optional=True)
        super().__init__(
            device=torch.device("cpu") if device is None else device, batch_size=batch_size
        )
        # EnvBase keeps batch_locked on the class; keep ours on the instance.
        self.__dict__["_batch_locked"] = bool(batch_locked)
        self.max_steps = int(max_steps)
        self.terminate_on_success = bool(terminate_on_success)
        self.rng = torch.Generator(device=self.device)
        self._emitted = _EmittedTensors()
        self._make_specs()
        self.set_seed(torch.empty((), dtype=torch.int64).random_().item() if seed is None else seed)

    # ------------------------------------------------------------------ #
    # What subclasses describe
    # ------------------------------------------------------------------ #
    @property
    def num_actions(self) -> int:
        raise NotImplementedError

    @property
    def state_shape(self) -> torch.Size:
        """Per-item shape of ``state`` (without batch dimensions)."""
        raise NotImplementedError

    def _state_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Elementwise (low, high) of ``state`` for its spec."""
        raise NotImplementedError

    def sample_states(self, shape: torch.Size) -> torch.Tensor:
        """Random valid start configurations, int64 ``[*shape, *state_shape]``."""
        raise NotImplementedError

    def sample_goal_states(self, shape: torch.Size) -> torch.Tensor:
        """Random valid goal configurations (defaults to :meth:`sample_states`)."""
        return self.sample_states(shape)

    def transition(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Next configuration. ``state`` ``[*B, *state_shape]``, ``action`` ``[*B]``."""
        raise NotImplementedError

    def transitions(self, state: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The configurations after each of ``H`` actions: :meth:`transition` ``H`` times.

        Args:
            state: int64 ``[*B, *state_shape]``, broadcast against ``actions[..., 0]``.
            actions: int64 ``[*L, H]``.

        Returns:
            int64 ``[*L, H, *state_shape]``. Subclasses may roll out faster, with the
            same result.
        """
        lead = actions.shape[:-1]
        current = state.expand(*lead, *self.state_shape)
        steps = []
        for t in range(actions.shape[-1]):
            current = self.transition(current, actions[..., t])
            steps.append(current)
        return torch.stack(steps, dim=len(lead))

    def render_state(self, state: torch.Tensor) -> torch.Tensor:
        """Draws any batch of states: int64 ``[*B, *state_shape]`` -> uint8 ``[*B, 3, 16, 16]``."""
        raise NotImplementedError

    def invalid_states(self, state: torch.Tensor) -> torch.Tensor:
        """bool ``[*B]``: which configurations break the rules (overlap, wall, off-grid)."""
        raise NotImplementedError

    def frame_parts(self, state: torch.Tensor) -> torch.Tensor | None:
        """The pre-drawn parts whose sum is each frame: int64 ``[*B, P]``, or ``None``.

        An env that draws a valid state as the sum of ``P`` rows of
        :meth:`frame_part_table` whose non-black bytes never overlap (so that
        ``render_state(state)`` equals their byte-wise sum, without carries) returns the
        rows' indices. Whatever is linear in a frame's bytes (a hash of them, the dot
        product with a goal image) then follows from ``P`` table entries, without drawing
        the frame: planning through the true dynamics uses this. ``None`` (the default)
        says the env draws its frames some other way.
        """
        return None

    def frame_part_table(self) -> torch.Tensor | None:
        """uint8 ``[T, 3, 16, 16]``: the parts :meth:`frame_parts` indexes (``None`` if unused)."""
        return None

    def lower_bound_steps(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        """int64 ``[*B]``: a lower bound on the steps from ``state`` to ``goal_state``.

        Both are checked first (:meth:`check_state`: layout and the env's rules) and must
        have the same shape ``[*B, *state_shape]``: a bound between states of other worlds,
        or off the grid, would be a number that means nothing.
        """
        state = self.check_state(state, "state")
        goal_state = self.check_state(goal_state, "goal_state")
        if state.shape != goal_state.shape:
            raise ValueError(
                f"state and goal_state must have the same shape, got {list(state.shape)} and "
                f"{list(goal_state.shape)}."
            )
        return self._lower_bound_steps(state, goal_state)

    def _lower_bound_steps(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        """:meth:`lower_bound_steps` on checked states of one shape."""
        raise NotImplementedError

    def true_dynamics(self) -> EnvBase:
        """This world's dynamics as a planning env (:class:`~dorp_rl.envs.GroundTruthModelEnv`,
        vectorised), what ``make_planning_env(env, "gt")`` uses."""
        from dorp_rl.envs.planning import GroundTruthModelEnv

        return GroundTruthModelEnv(self)

    def config(self) -> dict:
        """JSON-able description of the world (class and layout options, not batch or seed).

        Data sets and checkpoints store it, so that loading them next to another
        environment fails with a message saying what differs.
        """
        return {"env": type(self).__name__}

    def play_copy(self, trajectory_length: int | None = None) -> GridWorldEnv:
        """A copy set up for play data: episodes of ``trajectory_length`` steps (default
        :attr:`PLAY_TRAJECTORY_LENGTH`) that do not stop at the goal.

        :func:`~dorp_rl.data.play_env` calls it; an env without it is wrapped in
        torchrl's ``StepCounter`` instead.
        """
        length = check_int("trajectory_length", trajectory_length, low=1, optional=True)
        length = self.PLAY_TRAJECTORY_LENGTH if length is None else length
        if self.batch_size == torch.Size([]) and not self.batch_locked:
            raise ValueError("env must be batch-locked to collect play data (batch_locked=True).")
        out = copy.deepcopy(self)
        out.max_steps = length
        out.terminate_on_success = False
        return out

    # ------------------------------------------------------------------ #
    # Which frames this world can show
    # ------------------------------------------------------------------ #
    def frame_colours(self) -> torch.Tensor | None:
        """uint8 ``[K, 3]``: every colour the renderer draws, black first (``None``: unknown).

        Read off :meth:`frame_part_table` (computed once); an env without one overrides it.
        """
        cached = self.__dict__.get("_frame_colours")
        if cached is None:
            table = self.frame_part_table()
            if table is None:
                return None
            codes = colour_codes(table).unique()  # sorted: black (0) first if drawn
            codes = torch.cat([codes.new_zeros(1), codes[codes != 0]])
            cached = torch.stack([(codes >> 16) & 255, (codes >> 8) & 255, codes & 255], -1)
            cached = cached.to(torch.uint8)
            self.__dict__["_frame_colours"] = cached
        return cached

    def states_from_frames(self, frames: torch.Tensor) -> torch.Tensor | None:
        """The state each frame shows, int64 ``[*B, *state_shape]`` (``None``: not readable).

        A best guess read off uint8 frames ``[*B, 3, 16, 16]`` (where each object's colour
        first appears); :meth:`invalid_frames` keeps only the frames that are exactly the
        render of a valid state.
        """
        return None

    def invalid_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """bool ``[*B]``: which uint8 frames ``[*B, 3, 16, 16]`` no valid state of this env draws.

        A frame with a colour the renderer never uses is refused; where
        :meth:`states_from_frames` reads a state, so is any frame that is not exactly the
        render of a valid state (a block missing, cut or doubled, another layout).
        """
        frames = frames.to(self.device)
        bad = torch.zeros(frames.shape[:-3], dtype=torch.bool, device=self.device)
        colours = self.frame_colours()
        if colours is not None:
            bad |= foreign_colours(frames, colours)
        states = self.states_from_frames(frames)
        if states is not None:
            drawn = self.render_state(states.clamp_min(0))
            bad |= (drawn != frames).flatten(-3).any(-1) | self.invalid_states(states)
        return bad

    def check_frame(self, frames: torch.Tensor, name: str = "pixels") -> None:
        """Refuses frames that cannot come from this env (see :meth:`invalid_frames`).

        Reads the values (a device synchronisation): the policies and planners call it
        once per call on the goal and current frames, through
        :func:`dorp_rl.frames.check_task_frames`.
        """
        frames = check_frames(frames, name, shape=(3, self.grid_size, self.grid_size))
        bad = self.invalid_frames(frames)
        if not bool(bad.any()):
            return
        first = [int(i) for i in bad.nonzero()[0]] if bad.dim() else []
        frame = frames.to(self.device)[tuple(first)]
        colours = self.frame_colours()
        if colours is not None and bool(foreign_colours(frame, colours)):
            detail = describe_foreign_colours(frame, colours)
        else:
            detail = "its colours are the env's, but no valid configuration draws it"
        raise ValueError(
            f"{name} holds {int(bad.sum())} frame(s) that no valid state of "
            f"{self.describe_world()} draws (first at batch index {first}: {detail}). Is it "
            "a frame of another environment or setting (another layout, another number of "
            "objects)?"
        )

    def describe_world(self) -> str:
        """A short name of this world for messages (the class name; subclasses add options)."""
        return type(self).__name__

    # ------------------------------------------------------------------ #
    # Checks with errors that say what was expected
    # ------------------------------------------------------------------ #
    def check_state(self, state: torch.Tensor, name: str = "state") -> torch.Tensor:
        """Validates dtype, shape and rules of a batch of states and returns it on device.

        Reads the values (one device synchronisation): used at the boundary (``reset``
        with given states, states written into a tensordict before ``step``), never on
        the env's own outputs.
        """
        state = check_state_layout(state, self.state_shape, name, owner=type(self).__name__)
        state = state.to(self.device)
        bad = self.invalid_states(state)
        if bad.any():
            rows = bad.nonzero().tolist()
            first = rows[0] if bad.dim() > 0 else []
            raise ValueError(
                f"{name} holds {len(rows) or 1} invalid configuration(s) "
                f"({self._describe_invalid(state, bad)}); first at batch index {first}: "
                f"{state[tuple(first)].tolist()}."
            )
        return state

    def _describe_invalid(self, state: torch.Tensor, bad: torch.Tensor) -> str:
        return "breaks the environment's rules"

    def check_action(
        self, action: torch.Tensor, batch_shape: Sequence[int] | None = None
    ) -> torch.Tensor:
        """Validates an action tensor ``[*B, 1]`` (``B = batch_shape`` if given); returns int64 ``[*B]``."""
        shape = None if batch_shape is None else (*batch_shape, 1)
        return check_action(action, self.num_actions, shape=shape).squeeze(-1)

    # ------------------------------------------------------------------ #
    # EnvBase
    # ------------------------------------------------------------------ #
    def _make_specs(self) -> None:
        shape = self.batch_size
        low, high = self._state_bounds()
        image = Bounded(
            low=0, high=255, shape=(*shape, 3, self.grid_size, self.grid_size), dtype=torch.uint8
        )
        state = Bounded(
            low=low.expand(*shape, *self.state_shape),
            high=high.expand(*shape, *self.state_shape),
            dtype=torch.int64,
        )
        self.observation_spec = Composite(
            pixels=image,
            goal_pixels=image.clone(),
            state=state,
            goal_state=state.clone(),
            step_count=Unbounded(shape=(*shape, 1), dtype=torch.int64),
            success=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            shape=shape,
        )
        # Declared as state too, so `reset(td, set_state=True)` is TorchRL's way to pick them.
        self.state_spec = Composite(state=state.clone(), goal_state=state.clone(), shape=shape)
        self.action_spec = Categorical(self.num_actions, shape=(*shape, 1), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            truncated=Categorical(2, shape=(*shape, 1), dtype=torch.bool),
            shape=shape,
        )

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """Seeds the env's generator (an integer in ``[0, 2**63 - 1]``, or ``None``)."""
        return super().set_seed(check_seed(seed, optional=True), static_seed=static_seed)

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = torch.empty((), dtype=torch.int64).random_().item()
        self.rng.manual_seed(int(seed) % (2**63))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        set_state = bool(kwargs.get("set_state", False))
        if tensordict is not None and not self.batch_locked:
            shape = tensordict.batch_size
        else:
            shape = self.batch_size
        given = tensordict if (set_state and tensordict is not None) else None
        state = given.get("state", None) if given is not None else None
        goal_state = given.get("goal_state", None) if given is not None else None
        # Partial reset: only the flagged rows are kept by EnvBase, so only they are sampled.
        rows = tensordict.get("_reset", None) if tensordict is not None else None
        rows = None if rows is None or rows.all() else rows.reshape(shape)
        state = (
            self._sample_rows(self.sample_states, shape, rows)
            if state is None
            else self.check_state(state, "state").expand(*shape, *self.state_shape).clone()
        )
        goal_state = (
            self._sample_rows(self.sample_goal_states, shape, rows)
            if goal_state is None
            else self.check_state(goal_state, "goal_state")
            .expand(*shape, *self.state_shape)
            .clone()
        )
        success = self._success(state, goal_state)
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        self._emitted.add(state, goal_state)
        return TensorDict(
            pixels=self.render_state(state),
            goal_pixels=self.render_state(goal_state),
            state=state,
            goal_state=goal_state,
            step_count=torch.zeros((*shape, 1), dtype=torch.int64, device=self.device),
            success=success,
            done=false,
            terminated=false.clone(),
            truncated=false.clone(),
            batch_size=shape,
            device=self.device,
        )

    def _sample_rows(self, sampler, shape: torch.Size, rows: torch.Tensor | None) -> torch.Tensor:
        """``sampler`` for the rows flagged in ``rows`` (all rows if ``None``); others hold zeros."""
        if rows is None:
            return sampler(shape)
        out = torch.zeros((*shape, *self.state_shape), dtype=torch.int64, device=self.device)
        out[rows] = sampler(torch.Size([int(rows.sum())]))
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        action = self.check_action(tensordict.get("action"), shape)
        state = self._trusted_state(tensordict, "state")
        goal_state = self._trusted_state(tensordict, "goal_state")
        step_count = tensordict.get("step_count", None)
        if step_count is None:
            step_count = torch.zeros((*shape, 1), dtype=torch.int64, device=self.device)
        next_state = self.transition(state, action)
        success = self._success(next_state, goal_state)
        step_count = step_count + 1
        terminated = success & self.terminate_on_success
        truncated = (step_count >= self.max_steps) & ~terminated
        goal_pixels = tensordict.get("goal_pixels", None)
        if goal_pixels is None:
            goal_pixels = self.render_state(goal_state)
        self._emitted.add(next_state, goal_state)
        return TensorDict(
            pixels=self.render_state(next_state),
            goal_pixels=goal_pixels,
            state=next_state,
            goal_state=goal_state,
            step_count=step_count,
            success=success,
            reward=success.to(torch.float32),
            done=terminated | truncated,
            terminated=terminated,
            truncated=truncated,
            batch_size=shape,
            device=self.device,
        )

    def _assert_tensordict_shape(self, tensordict: TensorDictBase) -> None:
        if (
            self.batch_locked or self.batch_size != ()
        ) and tensordict.batch_size != self.batch_size:
            raise BatchShapeError(
                f"the tensordict has batch_size {list(tensordict.batch_size)}, this "
                f"{type(self).__name__} has batch_size {list(self.batch_size)} (one row per env)."
            )

    def _trusted_state(self, tensordict: TensorDictBase, key: str) -> torch.Tensor:
        """``tensordict[key]``, checked unless it is a state this env produced and nobody changed."""
        value = tensordict.get(key, None)
        if value is None:
            raise MissingKeyError(
                f"{type(self).__name__}.step needs {key!r} in the tensordict (reset() writes it)."
            )
        if value in self._emitted:
            return value
        value = self.check_state(value, key)
        shape = (*tensordict.batch_size, *self.state_shape)
        if tuple(value.shape) != shape:
            raise ValueError(f"{key} must have shape {list(shape)}, got {list(value.shape)}.")
        return value

    def _success(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        dims = tuple(range(-len(self.state_shape), 0))
        return (state == goal_state).all(dim=dims).unsqueeze(-1)

    # ------------------------------------------------------------------ #
    # Helpers for subclasses
    # ------------------------------------------------------------------ #
    def _coords(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Row and column index grids, each int64 ``[16, 16]``."""
        idx = torch.arange(self.grid_size, device=self.device)
        return idx.view(-1, 1).expand(self.grid_size, self.grid_size), idx.view(1, -1).expand(
            self.grid_size, self.grid_size
        )


def draw_grid_tasks(env: GridWorldEnv, num_tasks: int, seed: int) -> TensorDict:
    """``num_tasks`` start/goal pairs from ``env``'s start and goal distributions, drawn
    with ``seed`` (the env's own generator is left as it was); goals equal to their start
    are redrawn. Holds ``state``, ``goal_state`` and ``lower_bound`` (int64).

    The task drawing of the grid worlds' profiles.
    """
    saved = env.rng.get_state()
    env.rng.manual_seed(int(seed))
    try:
        shape = torch.Size([int(num_tasks)])
        state = env.sample_states(shape)
        goal = env.sample_goal_states(shape)
        for _ in range(100):
            same = env.lower_bound_steps(state, goal) == 0
            if not bool(same.any()):
                break
            goal[same] = env.sample_goal_states(torch.Size([int(same.sum())]))
        else:
            raise RuntimeError("could not draw goals different from their starts.")
    finally:
        env.rng.set_state(saved)
    return TensorDict(
        state=state,
        goal_state=goal,
        lower_bound=env.lower_bound_steps(state, goal).reshape(shape).to(torch.int64),
        batch_size=shape,
    )
