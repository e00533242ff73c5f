"""How the DORP policy fared on each task, read from the state it left in the tensordict.

:func:`task_records` turns the last step of each task into one dict (why the task was
given up, in which phase it ended, and the loop's counts);
:func:`~dorp_rl.eval.evaluate_policy` puts them into its ``records`` and the
reproduction writes them to ``tasks.csv``.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from dorp_rl.policies.records import task_records
    >>> from dorp_rl.policies.state import PolicyState, loop_state_keys
    >>> state = PolicyState(loop_state_keys(num_onehots=2, max_removed_edges=4))
    >>> last = TensorDict({key: torch.zeros(2, 1, dtype=torch.long) for key in state.names()}, [2])
    >>> last["dorp_end"][1] = 1  # no path left ...
    >>> last["dorp_end_group"][0] = -1  # ... for group 0 of the second task
    >>> [(r["outcome"], r["group"]) for r in task_records(state, last)]
    [(None, None), ('no_path', 0)]
"""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase

from dorp_rl.policies.state import ENDINGS, MODES, PolicyState
from dorp_rl.validation import MissingKeyError

__all__ = ["task_records"]

#: The counts of a record and the state key each is read from.
_COUNTS = {
    "edge_removals": "dorp_replans",
    "reentries": "dorp_reentries",
    "plans": "dorp_plans",
    "waypoints": "dorp_waypoints",
    "waypoint_steps": "dorp_waypoint_steps",
    "goal_steps": "dorp_goal_steps",
    "relaxed": "dorp_relaxed",
}


def task_records(state: PolicyState, last: TensorDictBase) -> list[dict[str, Any]]:
    """One record per task, from the tensordicts of the tasks' last steps.

    Args:
        state: the policy's state declaration (a key it does not declare, kept by a
            rule the policy does not have, counts 0).
        last: ``[N]`` tensordict of one step per task (the step the task ended at),
            holding the policy's state keys.

    Returns:
        One dict per task: ``outcome`` (``"no_path"``, ``"goal_stalled"`` or
        ``"removal_limit"`` when the policy gave the task up, ``None`` when it did not),
        ``group`` (the group left without a path, or whose hop hit the removal limit;
        ``None``), ``phase`` (the :data:`~dorp_rl.policies.state.MODES` name at that
        step), and the counts ``edge_removals``, ``reentries``, ``plans`` (waypoint plans
        made), ``waypoints`` (reached), ``waypoint_steps``, ``goal_steps`` and
        ``relaxed``.

    Raises:
        MissingKeyError: ``last`` lacks a key the policy declares (not a step of this
            policy).
    """
    n = last.shape[0]

    def column(key: str) -> list[int]:
        if key not in state:
            return [0] * n  # kept by a rule this policy does not have
        value = last.get(key, None)
        if value is None:
            raise MissingKeyError(
                f"task_records needs {key!r}: was the step planned by this policy?"
            )
        return value.reshape(n, -1)[:, 0].long().tolist()

    endings = {v: k for k, v in ENDINGS.items()}
    phases = {v: k for k, v in MODES.items()}
    ends, groups, modes = column("dorp_end"), column("dorp_end_group"), column("dorp_mode")
    counts = {name: column(key) for name, key in _COUNTS.items()}
    return [
        {
            "outcome": None
            if ends[i] == ENDINGS["running"]
            else endings.get(ends[i], str(ends[i])),
            "group": None if groups[i] < 0 else groups[i],
            "phase": phases.get(modes[i], str(modes[i])),
            **{name: values[i] for name, values in counts.items()},
        }
        for i in range(n)
    ]
