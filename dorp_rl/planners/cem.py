"""Cross-entropy method over per-step categorical distributions (discrete CEM).

Each optimisation step's candidates are rolled out and scored by
:class:`~dorp_rl.planners.DiscreteMPCPlanner`: into one :class:`~dorp_rl.planners.CandidateRollout` (through the env's
``imagine_candidates`` when it declares one, else by stepping it) that the cost reads
(``base.py``'s docstring has the contract).
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from dorp_rl.planners.base import DiscreteMPCPlanner, improves, select_best
from dorp_rl.validation import check_bool, check_float, check_int

__all__ = ["CategoricalCEMPlanner"]


class CategoricalCEMPlanner(DiscreteMPCPlanner):
    """Cross-entropy method over independent per-decision categorical distributions.

    The discrete counterpart of :class:`torchrl.modules.planners.CEMPlanner` (same
    argument names). Each of the ``optim_steps`` steps samples ``num_candidates``
    sequences from per-decision categorical distributions ``[B, H / r, A]`` (uniform at
    first), scores them, and refits each distribution to the action frequencies of the
    ``top_k`` lowest-scoring sequences (the elites), optionally mixed with the previous
    distribution (``smoothing``) and floored at ``min_probability`` so that no action
    becomes impossible. The best sequence seen in any step is the plan. The paper's
    VF-CEM: 1000 samples, top 2 % (``top_k=20``), 3 steps.

    Warm start (``warm_start=True``): a row that has a plan from an earlier call starts
    from it shifted by the steps executed since (padded with its last action), as
    ``warm_start_mix * one_hot(shifted plan) + (1 - warm_start_mix) * uniform``.

    Args:
        env: the planning env (not batch-locked, Categorical action).
        cost: a TensorDict module writing a per-step cost ``[B, N, H]`` under
            ``cost_key`` (:mod:`dorp_rl.planners.costs`).
        planning_horizon: env steps per sequence (``H``, default 14).
        num_candidates: sequences per row and optimisation step (``N``, default 1000).
        action_repeat: env steps per decision; must divide ``planning_horizon``.
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
        optim_steps: CEM iterations (default 3).
        top_k: number of elites the distributions are refitted to, in
            ``[1, num_candidates]`` (default 20, 2 % of 1000).
        warm_start: start from the previous plan shifted (see above).
        warm_start_mix: weight of the shifted plan in the initial distribution, in [0, 1].
        smoothing: weight of the old distribution in each refit, in [0, 1).
        min_probability: floor of every action probability after a refit, in
            ``[0, 1 / num_actions]``.

    Examples:
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.planners import CategoricalCEMPlanner, PixelDistanceCost
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> planner = CategoricalCEMPlanner(
        ...     GroundTruthModelEnv(env),
        ...     PixelDistanceCost(),
        ...     planning_horizon=6,
        ...     num_candidates=100,
        ...     seed=0,
        ...     optim_steps=3,
        ...     top_k=10,
        ... )
        >>> td = env.rollout(3, planner)
        >>> td["action"].shape, bool(((td["action"] >= 0) & (td["action"] < 4)).all())
        (torch.Size([2, 3, 1]), True)
    """

    def __init__(
        self,
        env: EnvBase,
        cost: nn.Module,
        *,
        planning_horizon: int = 14,
        num_candidates: int = 1000,
        action_repeat: int = 1,
        execution: str = "receding",
        step_aggregation: str | None = None,
        seed: int | None = None,
        cost_key: NestedKey | None = None,
        action_key: NestedKey = "action",
        key_prefix: str = "planner_",
        action_prior_key: NestedKey | None = None,
        excluded_actions_key: NestedKey | None = None,
        prune: bool = False,
        optim_steps: int = 3,
        top_k: int = 20,
        warm_start: bool = True,
        warm_start_mix: float = 0.5,
        smoothing: float = 0.0,
        min_probability: float = 1e-3,
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
        self.optim_steps = check_int("optim_steps", optim_steps, low=1)
        self.top_k = check_int("top_k", top_k, low=1, high=self.num_candidates)
        self.warm_start = check_bool("warm_start", warm_start)
        self.warm_start_mix = check_float("warm_start_mix", warm_start_mix, low=0.0, high=1.0)
        self.smoothing = check_float("smoothing", smoothing, low=0.0, high=1.0, high_open=True)
        self.min_probability = check_float(
            "min_probability", min_probability, low=0.0, high=1.0 / self.num_actions
        )

    def initial_probs(
        self,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
        prior: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Initial per-decision distributions ``[b, H / r, A]`` (uniform or the rows'
        ``prior``, warm-started).

        Args:
            previous_plan: int64 ``[b, H]``, the stored plans (per env step).
            shift: int64 ``[b]``, env steps executed since each was planned.
            valid: bool ``[b]``, which rows have a plan.
            prior: ``[b, A]`` action distributions to start from (``None``: uniform).
        """
        rows = previous_plan.shape[0]
        a, h = self.num_actions, self.planning_horizon
        device = previous_plan.device
        if prior is None:
            uniform = torch.full((rows, self.num_decisions, a), 1.0 / a, device=device)
        else:
            uniform = prior.to(device).unsqueeze(1).expand(-1, self.num_decisions, -1).clone()
        use = valid & (shift < h) if self.warm_start else torch.zeros_like(valid)
        if not use.any():
            return uniform
        steps = torch.arange(h, device=device) + shift.clamp(0, h - 1).unsqueeze(-1)
        shifted = previous_plan.gather(-1, steps.clamp_max(h - 1))  # pads with the last action
        starts = shifted[:, :: self.action_repeat]  # first env step of each decision
        onehot = torch.nn.functional.one_hot(starts, a).to(uniform.dtype)
        warm = self.warm_start_mix * onehot + (1.0 - self.warm_start_mix) * uniform
        return torch.where(use.view(-1, 1, 1), warm, uniform)

    def _sample(self, probs: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Inverse-CDF samples ``[b, N, D]`` from ``probs [b, D, A]`` and uniforms ``[b, N, D]``."""
        cdf = probs.cumsum(-1)  # [b, D, A], non-decreasing
        # The number of CDF entries <= u, found by binary search per (row, decision).
        index = torch.searchsorted(cdf, u.transpose(1, 2).contiguous(), right=True)
        return index.transpose(1, 2).clamp_max(self.num_actions - 1).contiguous()

    def _refit(self, probs: torch.Tensor, elites: torch.Tensor) -> torch.Tensor:
        """Distributions ``[b, D, A]`` refitted to elites ``[b, top_k, D]``."""
        freq = torch.nn.functional.one_hot(elites, self.num_actions).to(probs.dtype).mean(1)
        probs = self.smoothing * probs + (1.0 - self.smoothing) * freq
        probs = probs.clamp_min(self.min_probability)
        return probs / probs.sum(-1, keepdim=True)

    def _optimize(
        self,
        td: TensorDictBase,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rows = td.batch_size[0]
        probs = self.initial_probs(previous_plan, shift, valid, self.action_prior(td))
        excluded = self.excluded_actions(td)
        u = self._uniforms(rows, self.optim_steps)
        index = torch.arange(rows, device=probs.device)
        best_decisions = best_score = best_step = None
        for i in range(self.optim_steps):
            if excluded is not None:  # after a refit too: min_probability gives them mass
                probs[:, 0] = self.first_decision_probs(probs[:, 0], excluded)
            decisions = self._sample(probs, u[:, i])
            score, step = self._evaluate(td, decisions)
            best = select_best(score, step)
            cand_decisions, cand_score, cand_step = (
                decisions[index, best],
                score[index, best],
                step[index, best],
            )
            if best_score is None:
                best_decisions, best_score, best_step = cand_decisions, cand_score, cand_step
            else:
                better = improves(cand_score, cand_step, best_score, best_step)
                best_decisions = torch.where(better.unsqueeze(-1), cand_decisions, best_decisions)
                best_score = torch.where(better, cand_score, best_score)
                best_step = torch.where(better, cand_step, best_step)
            if i + 1 < self.optim_steps:
                elite_index = score.topk(self.top_k, dim=-1, largest=False).indices
                elites = decisions.gather(
                    1, elite_index.unsqueeze(-1).expand(-1, -1, self.num_decisions)
                )
                probs = self._refit(probs, elites)
        return best_decisions, best_score, best_step

    def extra_repr(self) -> str:
        return (
            f"{super().extra_repr()}, optim_steps={self.optim_steps}, top_k={self.top_k}, "
            f"warm_start={self.warm_start}"
        )
