"""Goal-conditioned TorchRL env over a gymnasium env whose state is its Python object.

torchrl's ``GymEnv`` gives frames and actions of a gymnasium env, enough for play data
and codes, but no ``state`` entry, no goals and no way to start from a given state, which
tasks and the true dynamics need. :class:`GymGoalEnv` adds them from two functions of the
gymnasium env: ``state_of(gym_env)``, its state as a few integers, and, when the env
allows it, ``set_state(gym_env, state)``. Without ``set_state`` the env is copied: every
state reached keeps a ``copy.deepcopy`` of the env in it (a snapshot), and a step from a
state steps a copy of its snapshot.

Either way each ``(state, action)`` is stepped in the gymnasium env once and remembered,
and each state drawn once: planners imagine thousands of candidates from few distinct
states, so after the first plans a rollout is table lookups (``docs/NOTES.md`` has the
measurements). The env is stateless in TorchRL's sense (a step reads ``state`` from the
tensordict), so with ``batch_size=()`` and ``batch_locked=False`` it is its own true
dynamics for planning.
"""

from __future__ import annotations

import copy
import random
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.envs.grid_base import CheckedRolloutLength
from dorp_rl.envs.planning import distinct_rows
from dorp_rl.envs.spec import qualified_name
from dorp_rl.frames import frames_to_uint8

__all__ = ["GymGoalEnv", "draw_reachable_tasks"]


def _distinct(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Distinct rows of an int64 ``[n, D]`` tensor and the inverse (``None``: all rows
    kept, after a hash collision), grouped by a hash of their bytes (no row sort)."""
    distinct, inverse = distinct_rows(rows.contiguous().view(torch.uint8))
    return distinct.view(torch.int64), inverse


class _Dynamics:
    """The remembered dynamics of one gymnasium env: transitions, frames, reachable states."""

    def __init__(
        self,
        make_gym_env: Callable[[], Any],
        state_of: Callable[[Any], Sequence[int]],
        set_state: Callable[[Any, Sequence[int]], None] | None,
    ) -> None:
        self.gym_env = make_gym_env()
        self.state_of = state_of
        self.set_state = set_state
        self.gym_env.reset()
        self.start = tuple(int(v) for v in state_of(self.gym_env))
        self.snapshots: dict[tuple, Any] = {}
        if set_state is None:
            self.snapshots[self.start] = copy.deepcopy(self.gym_env)
        self.steps: dict[tuple, tuple] = {}
        self.frames: dict[tuple, np.ndarray] = {}
        self._reachable: list[tuple] | None = None
        self._distances: dict[tuple, dict[tuple, int]] = {}
        #: gymnasium steps and renders made (the cost the tables save)
        self.gym_calls = 0

    def _at(self, state: tuple) -> Any:
        if self.set_state is not None:
            self.set_state(self.gym_env, state)
            return self.gym_env
        if state not in self.snapshots:
            raise ValueError(
                f"state {list(state)} was never reached: an env that can only be copied "
                "starts from states it has seen (its reachable states)."
            )
        return copy.deepcopy(self.snapshots[state])

    def step(self, state: tuple, action: int) -> tuple:
        key = (*state, action)
        if key not in self.steps:
            env = self._at(state)
            env.step(action)
            self.gym_calls += 1
            nxt = tuple(int(v) for v in self.state_of(env))
            if self.set_state is None and nxt not in self.snapshots:
                self.snapshots[nxt] = env
            self.steps[key] = nxt
        return self.steps[key]

    def frame(self, state: tuple) -> np.ndarray:
        if state not in self.frames:
            env = self._at(state)
            self.frames[state] = np.ascontiguousarray(env.render())
            self.gym_calls += 1
        return self.frames[state]

    def reachable(self, num_actions: int) -> list[tuple]:
        """Every state reachable from the start, in a fixed (sorted) order."""
        if self._reachable is None:
            self._reachable = sorted(self.distances(self.start, num_actions))
        return self._reachable

    def distances(self, start: tuple, num_actions: int) -> dict[tuple, int]:
        """Fewest steps from ``start`` to each reachable state (searched once per start)."""
        if start not in self._distances:
            self._distances[start] = self._search(start, num_actions)
        return self._distances[start]

    def _search(self, start: tuple, num_actions: int) -> dict[tuple, int]:
        dist, queue = {start: 0}, deque([start])
        while queue:
            state = queue.popleft()
            for action in range(num_actions):
                nxt = self.step(state, action)
                if nxt not in dist:
                    dist[nxt] = dist[state] + 1
                    queue.append(nxt)
        return dist


class GymGoalEnv(CheckedRolloutLength, EnvBase):
    """A gymnasium env as a batched, stateless, goal-conditioned TorchRL env.

    Keys: ``pixels`` / ``goal_pixels`` uint8 ``[*B, C, H, W]`` (the gymnasium env's
    ``render()``, channels first), ``state`` / ``goal_state`` int64 ``[*B, S]``
    (``state_of``), ``action`` int64 ``[*B, 1]``; ``done`` / ``terminated`` when the
    state equals the goal (for a goal given as an image only, ``goal_pixels`` without
    ``goal_state``: when the frame equals it). ``reset()`` draws start and goal uniformly
    from the states reachable from the gymnasium env's own reset (goal different from the
    start); ``reset(td, set_state=True)`` starts from ``td``'s ``state`` and
    ``goal_state`` (or keeps ``goal_pixels`` given without ``goal_state``).

    Args:
        make_gym_env: builds the gymnasium env (``render_mode="rgb_array"``); its reset
            must give the same situation every time (e.g. a fixed layout seed).
        state_of: ``gym_env -> ints``, everything that decides what happens next and
            what is drawn (for MiniGrid: agent cell and direction, key, door).
        set_state: ``(gym_env, state) -> None`` puts the env in ``state``; ``None``: the
            env is copied instead (snapshots of every state reached).
        batch_size: ``(n,)`` for ``n`` rows; ``()`` with ``batch_locked=False`` steps any
            leading shape (the true dynamics of a planner).
        seed: seeds the draws of :meth:`reset`.

    Examples:
        >>> import gymnasium as gym
        >>> from dorp_rl.envs import GymGoalEnv
        >>> class Walk(gym.Env):  # a counter on 0..4, moved by actions 0 (down), 1 (up)
        ...     action_space = gym.spaces.Discrete(2)
        ...     def reset(self, seed=None, options=None):
        ...         self.x = 0
        ...         return self.x, {}
        ...     def step(self, a):
        ...         self.x = min(max(self.x + (1 if a else -1), 0), 4)
        ...         return self.x, 0.0, False, False, {}
        ...     def render(self):
        ...         frame = np.zeros((1, 5, 3), np.uint8)
        ...         frame[0, self.x] = 255
        ...         return frame
        >>> import numpy as np
        >>> env = GymGoalEnv(Walk, lambda e: (e.x,), batch_size=(2,), seed=0)
        >>> td = env.reset()
        >>> td["pixels"].shape, td["state"].shape
        (torch.Size([2, 3, 1, 5]), torch.Size([2, 1]))
        >>> len(env.reachable_states())
        5
    """

    _supports_set_state = True

    def __init__(
        self,
        make_gym_env: Callable[[], Any],
        state_of: Callable[[Any], Sequence[int]],
        set_state: Callable[[Any, Sequence[int]], None] | None = None,
        *,
        batch_size: Sequence[int] = (),
        batch_locked: bool | None = None,
        seed: int = 0,
        device: Any = None,
    ) -> None:
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        if batch_locked is not None:
            self.__dict__["_batch_locked"] = bool(batch_locked)
        self.dynamics = _Dynamics(make_gym_env, state_of, set_state)
        self.make_gym_env = make_gym_env
        space = self.dynamics.gym_env.action_space
        if not hasattr(space, "n"):
            raise ValueError(
                f"the gymnasium env's action space must be Discrete, got {type(space).__name__}."
            )
        self.num_actions = int(space.n)
        frame = self.dynamics.frame(self.dynamics.start)
        if frame.ndim != 3 or frame.dtype != np.uint8:
            raise ValueError(
                "the gymnasium env's render() must give uint8 [H, W, C] frames "
                f"(render_mode='rgb_array'), got {frame.dtype} of shape {list(frame.shape)}."
            )
        h, w, c = frame.shape
        b = self.batch_size
        image = Bounded(0, 255, (*b, c, h, w), dtype=torch.uint8, device=self.device)
        size = len(self.dynamics.start)
        cells = Unbounded((*b, size), dtype=torch.int64, device=self.device)
        self.observation_spec = Composite(
            pixels=image, goal_pixels=image.clone(), state=cells, goal_state=cells.clone(), shape=b
        )
        self.action_spec = Categorical(self.num_actions, shape=(*b, 1), device=self.device)
        self.reward_spec = Unbounded((*b, 1), device=self.device)
        self.rng = random.Random(seed)

    def _set_seed(self, seed: int | None) -> None:
        self.rng = random.Random(0 if seed is None else int(seed))

    def config(self) -> dict:
        """The env's identity: the class, the gymnasium factory, frame and state shapes."""
        factory = self.make_gym_env
        return {
            "env": type(self).__name__,
            "gym_env": qualified_name(factory),
            "pixels": list(self.observation_spec["pixels"].shape[len(self.batch_size) :]),
            "state": list(self.observation_spec["state"].shape[len(self.batch_size) :]),
            "num_actions": self.num_actions,
        }

    # ------------------------------------------------------------------ dynamics
    def reachable_states(self) -> list[tuple]:
        """Every state reachable from the gymnasium env's reset, in a fixed order."""
        return self.dynamics.reachable(self.num_actions)

    def distance(self, start: Sequence[int], goal: Sequence[int]) -> int:
        """Fewest steps from ``start`` to ``goal`` (-1: unreachable)."""
        dist = self.dynamics.distances(tuple(int(v) for v in start), self.num_actions)
        return dist.get(tuple(int(v) for v in goal), -1)

    def render_states(self, state: torch.Tensor) -> torch.Tensor:
        """uint8 ``[*B, C, H, W]`` frames of int64 states ``[*B, S]`` (each distinct state
        drawn once: one lookup per distinct row, then a gather)."""
        shape = tuple(self.observation_spec["pixels"].shape[len(self.batch_size) :])
        rows = state.reshape(-1, state.shape[-1]).cpu()
        if rows.shape[0] == 0:
            return torch.zeros(*state.shape[:-1], *shape, dtype=torch.uint8, device=self.device)
        distinct, inverse = _distinct(rows)
        frames = np.stack([self.dynamics.frame(tuple(r)) for r in distinct.tolist()])
        out = torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()
        out = out if inverse is None else out.index_select(0, inverse)  # rows copied whole
        return out.reshape(*state.shape[:-1], *shape).to(self.device)

    def transition(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Next states int64 ``[*B, S]`` of states ``[*B, S]`` and actions ``[*B]`` (each
        distinct (state, action) looked up once, then a gather)."""
        rows = state.reshape(-1, state.shape[-1]).cpu().to(torch.int64)
        pairs = torch.cat([rows, action.reshape(-1, 1).cpu().to(torch.int64)], -1)
        distinct, inverse = _distinct(pairs)
        nxt = [self.dynamics.step(tuple(p[:-1]), int(p[-1])) for p in distinct.tolist()]
        out = torch.tensor(nxt, dtype=torch.int64).reshape(-1, rows.shape[-1])
        out = out if inverse is None else out[inverse]
        return out.reshape(state.shape).to(self.device)

    # ------------------------------------------------------------------ EnvBase
    def _draw(self, shape: torch.Size, avoid: torch.Tensor | None = None) -> torch.Tensor:
        states = self.reachable_states()
        n = int(torch.Size(shape).numel())
        drawn = []
        for i in range(n):
            while True:
                pick = states[self.rng.randrange(len(states))]
                if avoid is None or list(pick) != avoid.reshape(n, -1)[i].tolist():
                    break
            drawn.append(pick)
        return torch.tensor(drawn, dtype=torch.int64).reshape(*shape, len(states[0]))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size if tensordict is None else tensordict.batch_size
        given = tensordict if kwargs.get("set_state", False) else None
        state = None if given is None else given.get("state", None)
        goal = None if given is None else given.get("goal_state", None)
        goal_pixels = None if given is None else given.get("goal_pixels", None)
        state = self._draw(shape) if state is None else state.to(torch.int64).cpu()
        out = TensorDict(
            pixels=self.render_states(state),
            state=state.to(self.device),
            batch_size=shape,
            device=self.device,
        )
        if goal is None and goal_pixels is not None:  # a goal given as an image only
            frame = tuple(self.observation_spec["pixels"].shape[len(self.batch_size) :])
            goal_pixels = frames_to_uint8(goal_pixels, "goal_pixels", shape=frame)
            out.set("goal_pixels", goal_pixels.to(self.device).expand_as(out["pixels"]).clone())
            return out
        goal = self._draw(shape, avoid=state) if goal is None else goal.to(torch.int64).cpu()
        out.set("goal_pixels", self.render_states(goal))
        out.set("goal_state", goal.to(self.device))
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The next rows; solved where ``state == goal_state``, or, for a goal given as an
        image only (``goal_pixels`` without ``goal_state``), where the frame equals it."""
        shape = tensordict.batch_size
        state = tensordict.get("state").cpu()
        action = tensordict.get("action").to(torch.int64).reshape(shape).cpu()
        nxt = self.transition(state, action)
        pixels = self.render_states(nxt)
        goal = tensordict.get("goal_state", None)
        goal_pixels = tensordict.get("goal_pixels", None)
        out = TensorDict(pixels=pixels, state=nxt, batch_size=shape, device=self.device)
        if goal is not None:
            solved = (nxt == goal.to(nxt.device)).all(-1, keepdim=True)
            out.set("goal_state", goal)
        elif goal_pixels is not None:
            solved = (pixels == goal_pixels.to(pixels.device)).flatten(-3).all(-1, keepdim=True)
        else:
            solved = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        if goal_pixels is not None:
            out.set("goal_pixels", goal_pixels)
        out.update({"reward": solved.float(), "done": solved, "terminated": solved.clone()})
        return out


def draw_reachable_tasks(env: GymGoalEnv, num_tasks: int, seed: int) -> TensorDict:
    """``num_tasks`` tasks drawn with ``seed``: a start uniformly among the reachable
    states, a goal uniformly among the states reachable from it (not the start itself),
    with the exact ``lower_bound`` (the fewest steps, by breadth-first search over the
    remembered dynamics)."""
    states = env.reachable_states()
    rng = random.Random(int(seed))
    starts, goals, bounds = [], [], []
    for _ in range(int(num_tasks)):
        # A start from which some other state can be reached, then a goal among those.
        while True:
            start = states[rng.randrange(len(states))]
            dist = env.dynamics.distances(start, env.num_actions)
            reachable = sorted(state for state in dist if state != start)
            if reachable:
                break
        goal = reachable[rng.randrange(len(reachable))]
        starts.append(start)
        goals.append(goal)
        bounds.append(dist[goal])
    shape = torch.Size([int(num_tasks)])
    return TensorDict(
        state=torch.tensor(starts, dtype=torch.int64),
        goal_state=torch.tensor(goals, dtype=torch.int64),
        lower_bound=torch.tensor(bounds, dtype=torch.int64),
        batch_size=shape,
    )
