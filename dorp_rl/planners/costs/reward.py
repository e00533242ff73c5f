"""A cost from the planning env's reward (:class:`NegativeRewardCost`)."""

from __future__ import annotations

import torch
from tensordict import NestedKey, unravel_key

from dorp_rl.planners.costs.base import RolloutCost, get_rollout_key
from dorp_rl.planners.rollout import CandidateRollout

__all__ = [
    "NegativeRewardCost",
]


class NegativeRewardCost(RolloutCost):
    """Minus the planning env's reward at each step (for reward-defining model envs).

    Rewards after the first ``done`` of a candidate do not count (cost 0), as in
    torchrl's own ``CEMPlanner`` and ``MPPIPlanner``: the imagined rollout runs for the
    whole horizon, but an episode that ended earns nothing more. The reward of the step
    that sets ``done`` counts.

    Args:
        reward_key: the reward in the rollout, ``[*B, N, H]`` or ``[*B, N, H, 1]``.
        done_key: the done flag in the rollout (same shapes); ``None``: the planning env
            never ends an episode and every reward counts.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (default ``"sum"``: the return).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import NegativeRewardCost
        >>> done = torch.tensor([False, True, False, False]).expand(2, 5, 4).unsqueeze(-1)
        >>> rollout = TensorDict(
        ...     {("next", "reward"): torch.ones(2, 5, 4, 1), ("next", "done"): done},
        ...     batch_size=(2, 5, 4),
        ... )
        >>> NegativeRewardCost()(rollout)["cost"][0, 0]
        tensor([-1., -1.,  0.,  0.])
    """

    def __init__(
        self,
        reward_key: NestedKey = ("next", "reward"),
        *,
        done_key: NestedKey | None = ("next", "done"),
        out_key: NestedKey = "cost",
        step_aggregation: str = "sum",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        self.reward_key = unravel_key(reward_key)
        self.done_key = None if done_key is None else unravel_key(done_key)
        self.in_keys = [self.reward_key] + ([] if self.done_key is None else [self.done_key])

    def per_step_cost(self, rollout: CandidateRollout) -> torch.Tensor:
        name = type(self).__name__
        reward = get_rollout_key(rollout, self.reward_key, name)
        cost = -reward.reshape(rollout.batch_size).to(torch.float32)
        if self.done_key is not None:
            done = get_rollout_key(rollout, self.done_key, name)
            done = done.reshape(rollout.batch_size).to(torch.int64)
            # Steps after the first done along the horizon (the last batch dimension).
            ended = done.cumsum(-1) > done
            cost = cost.masked_fill(ended, 0.0)
        return cost

    def extra_repr(self) -> str:
        return f"reward_key={self.reward_key!r}, done_key={self.done_key!r}, {super().extra_repr()}"
