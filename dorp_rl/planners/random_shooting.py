"""Random shooting: the discrete planner that keeps the best of N random sequences.

Its candidates are rolled out and scored by :class:`~dorp_rl.planners.DiscreteMPCPlanner`:
into one :class:`~dorp_rl.planners.CandidateRollout` (through the env's
``imagine_candidates`` when it declares one, else by stepping it) that the cost reads
(``base.py``'s docstring has the contract).
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from dorp_rl.planners.base import DiscreteMPCPlanner, select_best
from dorp_rl.validation import check_float

__all__ = ["RandomShootingPlanner"]


class RandomShootingPlanner(DiscreteMPCPlanner):
    """Random shooting: ``num_candidates`` random action sequences, keep the best.

    The paper's VF-RS draws 1000 uniformly random sequences of 14 steps and executes the
    best one open loop. Each planning call draws one block of uniforms ``[B, 1, N, H / r]``
    from the planner's generator (two with ``action_persistence > 0``), so the same seed
    gives the same plans.

    With ``action_persistence = p``, each decision after the first repeats the previous
    one with probability ``p`` and is drawn uniformly otherwise: runs of one action are
    geometric with mean ``1 / (1 - p)``. Every sequence can still be drawn, but those that
    push one object several cells the same way, which uniform draws over many actions
    almost never hold, become common (``action_repeat`` fixes the run length instead).

    Args:
        env: the planning env (not batch-locked, Categorical action).
        cost: a TensorDict module writing a per-step cost ``[B, N, H]`` under
            ``cost_key`` (:mod:`dorp_rl.planners.costs`).
        planning_horizon: env steps per sequence (``H``, default 14).
        num_candidates: sequences per row (``N``, default 1000).
        action_repeat: env steps per decision; must divide ``planning_horizon``.
        action_persistence: probability in ``[0, 1)`` that a decision repeats the one
            before it (default 0: independent uniform decisions, as the paper).
        execution: ``"receding"`` (default) or ``"open_loop"``.
        step_aggregation: how a candidate's per-step costs fold into its score
            (``"min"``, ``"sum"`` or ``"final"``); ``None`` takes the cost's.
        seed: seeds the planner's generator.
        cost_key: the per-step cost key; ``None`` takes the cost's last ``out_keys``.
        action_key: where the action is written.
        key_prefix: prefix of the state keys (``planner_plan``, ...).
        action_prior_key: per-row action distributions ``[*B, A]`` to draw decisions from
            instead of uniformly (:class:`~dorp_rl.planners.DiscreteMPCPlanner`).
        excluded_actions_key: per-row bool ``[*B, A]``, actions a plan may not start
            with (:class:`~dorp_rl.planners.DiscreteMPCPlanner`).

    Examples:
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.planners import PixelDistanceCost, RandomShootingPlanner
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> planner = RandomShootingPlanner(
        ...     GroundTruthModelEnv(env),
        ...     PixelDistanceCost(),
        ...     planning_horizon=6,
        ...     num_candidates=100,
        ...     seed=0,
        ... )
        >>> td = env.rollout(3, planner)
        >>> td["action"].shape, td["planner_plan"].shape
        (torch.Size([2, 3, 1]), torch.Size([2, 3, 6]))
    """

    def __init__(
        self,
        env: EnvBase,
        cost: nn.Module,
        *,
        planning_horizon: int = 14,
        num_candidates: int = 1000,
        action_repeat: int = 1,
        action_persistence: float = 0.0,
        execution: str = "receding",
        step_aggregation: str | None = None,
        seed: int | None = None,
        cost_key: NestedKey | None = None,
        action_key: NestedKey = "action",
        key_prefix: str = "planner_",
        action_prior_key: NestedKey | None = None,
        excluded_actions_key: NestedKey | None = None,
        prune: bool = False,
    ) -> None:
        super().__init__(
            env,
            cost,
            planning_horizon=planning_horizon,
            num_candidates=num_candidates,
            action_repeat=action_repeat,
            execution=execution,
            step_aggregation=step_aggregation,
            seed=seed,
            cost_key=cost_key,
            action_key=action_key,
            key_prefix=key_prefix,
            action_prior_key=action_prior_key,
            excluded_actions_key=excluded_actions_key,
            prune=prune,
        )
        # the probability that a decision repeats the one before it
        self.action_persistence = check_float(
            "action_persistence", action_persistence, low=0.0, high=1.0, high_open=True
        )

    def _optimize(
        self,
        td: TensorDictBase,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rows = td.batch_size[0]
        u = self._uniforms(rows, 1)[:, 0]  # [b, N, D]
        prior = self.action_prior(td)
        if prior is None:
            decisions = (u * self.num_actions).floor().to(torch.int64)
        else:  # inverse CDF of each row's distribution
            cdf = prior.cumsum(-1).unsqueeze(1).expand(-1, u.shape[1], -1).contiguous()
            decisions = torch.searchsorted(cdf, u.contiguous(), right=True)
        excluded = self.excluded_actions(td)
        if excluded is not None:  # the first decision from the actions left (same draws)
            first = prior if prior is not None else torch.full_like(excluded, 1.0, dtype=u.dtype)
            cdf = self.first_decision_probs(first, excluded).cumsum(-1)
            decisions[..., 0] = torch.searchsorted(cdf, u[..., 0].contiguous(), right=True)
        decisions = decisions.clamp_max(self.num_actions - 1)
        if self.action_persistence > 0:
            repeat = self._uniforms(rows, 1)[:, 0] < self.action_persistence
            for t in range(1, decisions.shape[-1]):
                decisions[..., t] = torch.where(
                    repeat[..., t], decisions[..., t - 1], decisions[..., t]
                )
        score, step = self._evaluate(td, decisions)
        best = select_best(score, step)
        index = torch.arange(rows, device=best.device)
        return decisions[index, best], score[index, best], step[index, best]

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, action_persistence={self.action_persistence}"
