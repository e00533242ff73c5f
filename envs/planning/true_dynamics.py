"""The grid worlds' own dynamics as a planning env (:class:`GroundTruthModelEnv`): the
paper's ground-truth model.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite

from dorp_rl.envs.grid_base import (
    GridWorldEnv,
)
from dorp_rl.envs.planning.base import _FRAME, PlanningEnvBase, check_planning_action
from dorp_rl.envs.planning.imagined_frames import ImaginedFrames
from dorp_rl.frames import frames_to_uint8
from dorp_rl.validation import (
    check_state_layout,
)

__all__ = [
    "GroundTruthModelEnv",
]


class GroundTruthModelEnv(PlanningEnvBase):
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
