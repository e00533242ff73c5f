"""One declaration of a policy's per-env state: its keys, shapes, dtypes and reset values.

A policy that keeps state in the tensordict (plan progress, counters, flags) declares each
key once as a :class:`StateKey`; :class:`PolicyState` turns the declarations into the
``TensorDictPrimer`` torchrl's collectors and ``env.append_transform`` use, the values a
row restarts with, and the reading of a tensordict into flat ``[rows, width]`` tensors
(with the reset value for a key the tensordict lacks, and an error naming a key whose
shape does not fit). Nothing else lists the keys, so a part of the policy that adds a key
adds it in one place.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from dorp_rl.policies.state import PolicyState, StateKey
    >>> state = PolicyState([StateKey("steps"), StateKey("edge", fill=-1),
    ...                      StateKey("seen", torch.bool, width=3)])
    >>> values = state.read(TensorDict({"steps": torch.tensor([[4], [5]])}, [2]))
    >>> values["steps"].tolist(), values["edge"].tolist(), values["seen"].shape
    ([[4], [5]], [[-1], [-1]], torch.Size([2, 3]))
    >>> sorted(state.primer().primers.keys())
    ['edge', 'seen', 'steps']
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import TensorDictPrimer

__all__ = [
    "ENDINGS",
    "GOAL_PRIOR_KEY",
    "MODES",
    "NOOPS_KEY",
    "PLANNER_INPUTS",
    "PRIOR_KEY",
    "PolicyState",
    "StateKey",
    "loop_state_keys",
]

# The keys the policy's parts share with its planners (the rest are declared as
# StateKeys by the part that keeps them).
#: Where the policy writes the waypoint planner's action distribution (``action_prior_mix``).
PRIOR_KEY = "subgoal_action_prior"
#: Where the policy writes the goal planner's action distribution (``goal_action_prior_mix``).
GOAL_PRIOR_KEY = "goal_action_prior"
#: The actions seen to leave the current frame unchanged (kept by
#: :class:`~dorp_rl.policies.AvoidNoops`; the planners' ``excluded_actions_key``).
NOOPS_KEY = "dorp_noops"
#: The policy's state keys its planners may read (their costs' ``subgoal_code`` and
#: ``subgoal_mask``, the goal cost's weight, the excluded actions).
PLANNER_INPUTS = (
    "code",
    "goal_code",
    "subgoal_code",
    "subgoal_mask",
    "goal_code_weight",
    NOOPS_KEY,
)


@dataclass(frozen=True)
class StateKey:
    """One key of a policy's state: ``[*B, width]`` of ``dtype``, ``fill`` at reset."""

    name: str
    dtype: torch.dtype = torch.int64
    width: int = 1
    fill: float = 0
    doc: str = ""

    def __post_init__(self) -> None:
        if self.width < 1:
            raise ValueError(f"state key {self.name!r} needs width >= 1, got {self.width}.")

    def spec(self) -> Binary | Unbounded:
        """The key's spec without its batch dimensions."""
        if self.dtype is torch.bool:
            return Binary(n=self.width, shape=(self.width,), dtype=torch.bool)
        return Unbounded(shape=(self.width,), dtype=self.dtype)


class PolicyState:
    """The keys of a policy's state, in order; see the module docstring.

    Args:
        keys: the declarations; a name given twice is an error (two parts of a policy
            would write the same key).
    """

    def __init__(self, keys: Iterable[StateKey]) -> None:
        self.keys: dict[str, StateKey] = {}
        for key in keys:
            if key.name in self.keys:
                raise ValueError(f"state key {key.name!r} is declared twice.")
            self.keys[key.name] = key

    def __contains__(self, name: str) -> bool:
        return name in self.keys

    def names(self) -> list[str]:
        """The keys' names, in declaration order."""
        return list(self.keys)

    def primer(self) -> TensorDictPrimer:
        """A primer writing every key's reset value at ``reset`` (batch dims expanded)."""
        specs = Composite({name: key.spec() for name, key in self.keys.items()})
        defaults = {name: key.fill for name, key in self.keys.items()}
        return TensorDictPrimer(specs, default_value=defaults, expand_specs=True)

    def restart(self, values: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
        """Sets ``rows`` (a bool mask) of every key in ``values`` to its reset value."""
        for name, value in values.items():
            value[rows] = self.keys[name].fill

    def read(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        """Every key of ``td`` (batch ``[rows]``) as a CPU copy ``[rows, width]``; a missing
        key is its reset value.

        Raises:
            ValueError: a key whose shape is not ``[rows, width]`` (written by a policy
                with other sizes).
        """
        rows = td.batch_size[0]
        out = {}
        for name, key in self.keys.items():
            value = td.get(name, None)
            if value is None:
                out[name] = torch.full((rows, key.width), key.fill, dtype=key.dtype)
                continue
            if tuple(value.shape) != (rows, key.width):
                raise ValueError(
                    f"{name!r} must have shape [{rows}, {key.width}] for this policy, got "
                    f"{list(value.shape)}; was it written by a policy with other codes?"
                )
            out[name] = value.cpu().to(key.dtype).clone()
        return out


#: Values of ``dorp_mode``.
MODES = {"new": 0, "waypoint": 1, "goal": 2, "failed": 3, "done": 4}
#: Values of ``dorp_end``: why the policy gave a task up (the ``outcome`` of
#: :func:`~dorp_rl.policies.records.task_records`).
ENDINGS = {"running": 0, "no_path": 1, "goal_stalled": 2, "removal_limit": 3}


def loop_state_keys(num_onehots: int, max_removed_edges: int) -> list[StateKey]:
    """The keys the DORP loop (:class:`~dorp_rl.policies.AbstractGoalPolicy`) keeps for a
    graph of ``num_onehots`` one-hots (each recovery rule declares its own):

    =========================  ==================  =======================================
    key                        dtype / shape       meaning
    =========================  ==================  =======================================
    ``code``, ``goal_code``    int64 ``[C]``       codes of the current frame and the goal
    ``subgoal_code``           int64 ``[C]``       the waypoint (other one-hots: current)
    ``subgoal_mask``           bool ``[C]``        the one-hots the waypoint concerns
    ``dorp_mode``              int64 ``[1]``       0 new, 1 waypoint, 2 goal image,
                                                   3 failed, 4 done (:data:`MODES`)
    ``dorp_group``             int64 ``[1]``       group being moved
    ``dorp_distance``          int64 ``[1]``       hops left on its path (incl. waypoint)
    ``dorp_budget``            int64 ``[1]``       steps left to reach the waypoint
    ``dorp_edge``              int64 ``[1]``       graph edge of the current hop (-1: none)
    ``dorp_removed``           int64 ``[R]``       edges removed for this task (-1: free)
    ``dorp_replans``           int64 ``[1]``       edges removed so far
    ``dorp_stale_removals``    int64 ``[1]``       edges removed since the last waypoint
    ``dorp_waypoints``         int64 ``[1]``       waypoints reached so far
    ``dorp_plans``             int64 ``[1]``       waypoint plans made (fresh plans)
    ``dorp_waypoint_steps``    int64 ``[1]``       steps spent moving to waypoints
    ``dorp_goal_steps``        int64 ``[1]``       steps spent in the goal-image phase
    ``dorp_failed``            bool ``[1]``        the task is given up
    ``dorp_end``               int64 ``[1]``       why: 0 not given up, 1 no path left,
                                                   2 goal phase out of budget, 3 edge-
                                                   removal limit (:data:`ENDINGS`)
    ``dorp_end_group``         int64 ``[1]``       the group left without a path (-1: none)
    =========================  ==================  =======================================

    ``R`` is ``max(1, max_removed_edges)``.

    Examples:
        >>> [key.name for key in loop_state_keys(3, 8)][:4]
        ['code', 'goal_code', 'subgoal_code', 'subgoal_mask']
    """
    c, r = num_onehots, max(1, max_removed_edges)
    return [
        StateKey("code", width=c),
        StateKey("goal_code", width=c),
        StateKey("subgoal_code", width=c),
        StateKey("subgoal_mask", torch.bool, width=c),
        StateKey("dorp_mode"),
        StateKey("dorp_group"),
        StateKey("dorp_distance"),
        StateKey("dorp_budget"),
        StateKey("dorp_edge", fill=-1),
        StateKey("dorp_removed", width=r, fill=-1),
        StateKey("dorp_replans"),
        StateKey("dorp_stale_removals"),
        StateKey("dorp_waypoints"),
        StateKey("dorp_plans"),
        StateKey("dorp_waypoint_steps"),
        StateKey("dorp_goal_steps"),
        StateKey("dorp_failed", torch.bool),
        StateKey("dorp_end"),
        StateKey("dorp_end_group", fill=-1),
    ]
