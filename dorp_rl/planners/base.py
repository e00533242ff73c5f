"""Shared machinery of the discrete model-predictive planners (torchrl ``MPCPlannerBase``).

:class:`DiscreteMPCPlanner` is a :class:`torchrl.modules.planners.MPCPlannerBase` for a
:class:`~torchrl.data.Categorical` action: given the acting envs' tensordict (batch
``[B]``) it samples ``N`` candidate action sequences per row, rolls them out in a
planning env (:class:`~dorp_rl.envs.GroundTruthModelEnv`,
:class:`~dorp_rl.envs.VideoModelEnv`, or any non-batch-locked env) on a ``[B, N]``
batch, scores them with a cost module (:mod:`dorp_rl.planners.costs`) and writes an
``action``. The optimisers are :class:`~dorp_rl.planners.RandomShootingPlanner`
(``random_shooting.py``) and :class:`~dorp_rl.planners.CategoricalCEMPlanner`
(``cem.py``); torchrl's own ``CEMPlanner`` / ``MPPIPlanner`` assume continuous actions.
Argument names follow torchrl's: ``planning_horizon``, ``num_candidates``, and for CEM
``optim_steps`` and ``top_k``.

Planning horizon and action repeat
    ``planning_horizon`` counts env steps. With ``action_repeat = r`` a candidate is
    ``planning_horizon / r`` decisions, each repeated ``r`` times (the authors' 7
    actions x 2 = 14 steps); ``r`` must divide ``planning_horizon``.

Scoring
    The cost writes a per-step cost ``[B, N, H]`` into the rollout under ``cost_key``;
    ``step_aggregation`` (by default the cost's own ``step_aggregation`` attribute, else
    ``"sum"``) says how the ``H`` per-step costs of one candidate fold into its score:
    ``"sum"``, ``"final"`` (last step) or ``"min"`` (best step; among equal scores the
    candidate that gets there earliest wins). It is not a loss reduction: it decides
    which candidate is best, and for ``"min"`` how much of it is executed open loop.

Planning envs and costs: one rollout
    :meth:`DiscreteMPCPlanner.imagine` rolls the candidates out into one
    :class:`~dorp_rl.planners.CandidateRollout`, which every cost reads. It steps the
    env one horizon step at a time (``env.step`` / ``step_mdp``, any non-batch-locked
    torchrl ``EnvBase``) unless the env's class declares
    ``imagine_candidates(td, actions, next_keys)``: from the rows ``td [b]``, the actions
    ``[b, N, H]`` and the ``("next", key)`` entries the cost reads (``None``: all), it
    returns ``(rollout, lazy)``, a rollout ``[b, N, H]`` holding ``action`` and the
    values it computes, and a dict from the other requested keys to values computed on
    demand (:class:`~dorp_rl.envs.planning.LazyValue`, e.g. undrawn
    :class:`~dorp_rl.envs.planning.ImaginedFrames` for ``("next", "pixels")``); or
    ``None``, and the planner steps it
    (:meth:`~dorp_rl.envs.GroundTruthModelEnv.imagine_candidates` is one). The values
    must be those that stepping gives: the plans are the same either way. The
    declaration is looked up on the class (a ``TransformedEnv``, which forwards
    attributes to its base env, is stepped through its transforms). The cost runs
    through :func:`~dorp_rl.planners.score_rollout`.

Pruning
    With ``prune=True`` the best sequence of a call is shortened afterwards: each round
    scores the ``H / r`` sequences that drop one decision up to the best step (the
    rest moves up, the last decision is repeated to fill the horizon) and keeps the best
    of them if it scores lower, or as low at an earlier step; rounds stop when no drop
    helps. Random candidates carry detours (a move of another object, a move undone
    later) that cost nothing when the score only looks at the best step; pruning takes
    them out. It draws no random numbers, so the candidates of later calls are unchanged.

Execution
    ``"receding"``: every call replans and returns the first action of the best
    sequence. ``"open_loop"``: a call that finds no stored plan left plans, returns the
    first action and keeps the rest; following calls emit the stored actions one by one
    without planning, until the plan is used up. The whole sequence is kept for
    ``"sum"`` and ``"final"``; for ``"min"`` only the prefix up to the best step (going
    on would move away from the best predicted frame). Rows of a batch replan
    independently: only the rows whose plan ran out are planned.

State between calls (all in the tensordict, per row, prefix ``key_prefix``):

=====================  ==========================  =====================================
key                    dtype / shape               meaning
=====================  ==========================  =====================================
``planner_plan``       int64 ``[*B, H]``           best sequence of the last planning
                                                   call (per env step)
``planner_cursor``     int64 ``[*B, 1]``           actions of it emitted so far
``planner_length``     int64 ``[*B, 1]``           actions to execute open loop; 0 = no
                                                   plan yet (the primer's default)
``planner_cost``       float32 ``[*B, 1]``         score of that sequence
=====================  ==========================  =====================================

Nothing about a row lives in Python attributes, so the planners work with
``env.rollout``, batched envs and collectors. ``env.rollout`` carries these keys from
step to step on its own; a :class:`~torchrl.collectors.Collector` needs them declared
by a :class:`~torchrl.envs.TensorDictPrimer` on the env (:meth:`make_primer`; the
planners also expose it as ``make_tensordict_primer`` so that
``Collector(..., auto_register_policy_transforms=True)`` adds it, together with an
``InitTracker``). The primer zeroes the keys of rows that reset, and a row with
``is_init`` set (torchrl's :class:`~torchrl.envs.InitTracker`) drops its plan, so a new
episode never follows the previous episode's plan. Rows whose episode is over (root
``done``, or ``_step`` False in a batched ``env.rollout``) are not planned for
(:func:`finished_rows`): a batch costs only its unfinished rows.

Randomness
    A ``torch.Generator`` owned by the planner, seeded by ``seed`` (or by torch's global
    generator when ``seed=None``); :meth:`set_seed` reseeds it. The same seed and the
    same inputs give the same plans. Uniform numbers are drawn in one row-major block per
    call (``[B, optim_steps, N, H / r]``), so a row's candidates do not depend on the
    rows after it (row 0 planned alone or first in a batch sees the same samples), and no
    computation mixes rows: one row's goal never changes another row's plan.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, unravel_key
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TensorDictPrimer
from torchrl.modules.planners import MPCPlannerBase

from dorp_rl.frames import check_task_frames
from dorp_rl.planners.costs import (
    STEP_AGGREGATIONS,
    MissingRolloutKeyError,
    check_step_aggregation,
    score_rollout,
)
from dorp_rl.planners.rollout import CandidateRollout
from dorp_rl.validation import MissingKeyError, check_bool, check_int, check_seed

__all__ = [
    "EXECUTIONS",
    "STEP_AGGREGATIONS",
    "DiscreteMPCPlanner",
    "aggregate_steps",
    "check_step_aggregation",
    "improves",
    "select_best",
]

EXECUTIONS = ("receding", "open_loop")


class DiscreteMPCPlanner(MPCPlannerBase):
    """Shared machinery of the discrete planners: sampling, rollouts, scoring, state.

    Subclasses implement :meth:`_optimize` (random shooting, CEM). See the module
    docstring for the state keys, execution modes and randomness.

    Args:
        env: the planning env (not batch-locked, Categorical action of shape ``()`` or
            ``(1,)``).
        cost: a TensorDict module over the rollout ``[B, N, H]`` that writes a per-step
            cost ``[B, N, H]`` under ``cost_key`` (:mod:`dorp_rl.planners.costs`, a
            :class:`~dorp_rl.planners.CostSequence` of them, or any TensorDict module).
            Its ``in_keys`` say which predictions to stack and which root keys the
            acting tensordict must hold (all of them when it has none).
        planning_horizon: env steps per candidate sequence (``H``).
        num_candidates: sequences per row and per optimisation step (``N``).
        action_repeat: env steps per decision; must divide ``planning_horizon``.
        execution: ``"receding"`` or ``"open_loop"``.
        step_aggregation: how a candidate's per-step costs fold into its score,
            ``"min"``, ``"sum"`` or ``"final"``; ``None`` takes the cost's
            ``step_aggregation`` attribute (``"sum"`` if it has none).
        seed: seeds the planner's generator (``None``: drawn from torch's global one).
        cost_key: where the cost writes its per-step cost; ``None`` takes the cost's
            last ``out_keys`` entry (``"cost"`` if it has none).
        action_key: where the action is written.
        key_prefix: prefix of the state keys.
        prune: shorten the best sequence by dropping decisions while that lowers its
            score or reaches it earlier (see Pruning above).
        action_prior_key: a key of the acting tensordict holding, per row, a distribution
            over actions ``[*B, A]`` (non-negative, not all zero; normalised here) that
            the planner samples its candidates' actions from instead of uniformly
            (:meth:`action_prior`; random shooting draws every action from it, CEM starts
            from it). ``None`` (default): uniform draws.
        excluded_actions_key: a key of the acting tensordict holding, per row, bool
            ``[*B, A]``: actions a plan may not start with (:meth:`excluded_actions`;
            the DORP policy writes the actions seen to leave the current frame unchanged,
            which a learned model may believe move something). Candidates starting with
            one score ``inf``; random shooting and CEM draw their first decision from the
            others. ``None`` (default): every action may start a plan.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.planners import DiscreteMPCPlanner, PixelDistanceCost
        >>> class ActionZero(DiscreteMPCPlanner):  # one candidate: action 0 at every step
        ...     def _optimize(self, td, previous_plan, shift, valid):
        ...         decisions = torch.zeros(td.shape[0], 1, self.num_decisions, dtype=torch.int64)
        ...         score, step = self._evaluate(td, decisions)  # [b, 1] each
        ...         return decisions[:, 0], score[:, 0], step[:, 0]
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> planner = ActionZero(GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=3)
        >>> planner(env.reset())["planner_plan"]
        tensor([[0, 0, 0],
                [0, 0, 0]])
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
    ) -> None:
        if not isinstance(env, EnvBase):
            raise ValueError(f"env must be a torchrl EnvBase, got {type(env).__name__}.")
        if env.batch_locked:
            raise ValueError(
                f"the planning env {type(env).__name__} is batch-locked (batch_locked=True, "
                f"batch_size={tuple(env.batch_size)}): a planner steps a [B, N] batch of "
                "candidates in it, so it must accept any leading shape. Build it with "
                "batch_size=() and batch_locked=False, or wrap the env's dynamics in "
                "dorp_rl.envs.GroundTruthModelEnv / VideoModelEnv."
            )
        check_int("num_candidates", num_candidates, low=1)
        check_int("planning_horizon", planning_horizon, low=1)
        check_int("action_repeat", action_repeat, low=1)
        if int(planning_horizon) % int(action_repeat):
            raise ValueError(
                f"action_repeat must divide planning_horizon (it counts env steps: "
                f"planning_horizon / action_repeat decisions, each repeated action_repeat "
                f"times), got planning_horizon={planning_horizon} and "
                f"action_repeat={action_repeat}."
            )
        if execution not in EXECUTIONS:
            raise ValueError(f"execution must be one of {EXECUTIONS}, got {execution!r}.")
        if not callable(cost):
            raise ValueError(f"cost must be a callable module, got {type(cost).__name__}.")
        action_spec = env.full_action_spec[unravel_key(action_key)]
        if not isinstance(action_spec, Categorical) or tuple(action_spec.shape) not in ((), (1,)):
            raise ValueError(
                f"the planning env's action spec must be a Categorical of shape () or (1,), got "
                f"{type(action_spec).__name__} of shape {tuple(action_spec.shape)}."
            )
        cost_out_keys = [unravel_key(k) for k in (getattr(cost, "out_keys", None) or [])]
        if cost_key is None:
            cost_key = cost_out_keys[-1] if cost_out_keys else "cost"
        cost_key = unravel_key(cost_key)
        if cost_out_keys and cost_key not in cost_out_keys:
            raise ValueError(
                f"cost_key={cost_key!r} is not among the keys the cost "
                f"{type(cost).__name__} writes (out_keys={cost_out_keys}); pass the key "
                "holding its per-step cost."
            )
        super().__init__(env, action_key=action_key)
        self.action_key = unravel_key(action_key)
        self.cost = cost
        self.cost_key = cost_key
        self.num_actions = int(action_spec.n)
        self.num_candidates = int(num_candidates)
        self.planning_horizon = int(planning_horizon)
        self.action_repeat = int(action_repeat)
        self.num_decisions = self.planning_horizon // self.action_repeat
        self.execution = execution
        self.prune = check_bool("prune", prune)
        self.step_aggregation = check_step_aggregation(
            step_aggregation if step_aggregation is not None else _cost_aggregation(cost, cost_key)
        )
        self._action_shape = tuple(action_spec.shape)
        self.plan_key = f"{key_prefix}plan"
        self.cursor_key = f"{key_prefix}cursor"
        self.length_key = f"{key_prefix}length"
        self.plan_cost_key = f"{key_prefix}cost"
        self.state_keys = [self.plan_key, self.cursor_key, self.length_key, self.plan_cost_key]
        self._cost_keys = [unravel_key(k) for k in (getattr(cost, "in_keys", None) or [])]
        produced = {unravel_key(("next", k)) for k in self._env_output_keys()}
        self._next_keys = [k for k in self._cost_keys if isinstance(k, tuple) and k[0] == "next"]
        # Root keys the cost reads come from the acting tensordict (the action is ours).
        self._root_keys = [
            k for k in self._cost_keys if k not in self._next_keys and k != self.action_key
        ]
        for key in self._next_keys:
            if key not in produced:
                raise ValueError(
                    f"the cost reads {key!r}, which the planning env {type(env).__name__} does "
                    f"not produce (it produces {sorted(str(k) for k in produced)})."
                )
        self._env_in_keys = self._env_input_keys()
        self.action_prior_key = None if action_prior_key is None else unravel_key(action_prior_key)
        prior_keys = [] if self.action_prior_key is None else [self.action_prior_key]
        self.excluded_actions_key = (
            None if excluded_actions_key is None else unravel_key(excluded_actions_key)
        )
        if self.excluded_actions_key is not None:
            prior_keys.append(self.excluded_actions_key)
        self.in_keys = list(
            dict.fromkeys([*self._env_in_keys, *self._root_keys, *prior_keys, *self.state_keys])
        )
        self._frame_keys = self._find_frame_keys()
        self.out_keys = [self.action_key, *self.state_keys]
        self.generator = torch.Generator(device=env.device)
        self.set_seed(seed)

    # ------------------------------------------------------------------ #
    # Public helpers
    # ------------------------------------------------------------------ #
    def set_seed(self, seed: int | None) -> None:
        """Reseeds the planner's generator (``None``: a seed from torch's global generator)."""
        seed = check_seed(seed, optional=True)
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.generator.manual_seed(seed)

    def make_primer(self) -> TensorDictPrimer:
        """A :class:`~torchrl.envs.TensorDictPrimer` declaring the state keys (zeros at reset).

        Append it to the acting env (``env.append_transform(planner.make_primer())``)
        when a collector drives the planner; ``Collector(...,
        auto_register_policy_transforms=True)`` does it through
        :meth:`make_tensordict_primer`.
        """
        specs = Composite(
            {
                self.plan_key: Categorical(self.num_actions, shape=(self.planning_horizon,)),
                self.cursor_key: Unbounded(shape=(1,), dtype=torch.int64),
                self.length_key: Unbounded(shape=(1,), dtype=torch.int64),
                self.plan_cost_key: Unbounded(shape=(1,), dtype=torch.float32),
            }
        )
        return TensorDictPrimer(specs, default_value=0, expand_specs=True)

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Same as :meth:`make_primer`; the name torchrl's collectors look for."""
        return self.make_primer()

    # ------------------------------------------------------------------ #
    # MPCPlannerBase
    # ------------------------------------------------------------------ #
    def forward(
        self,
        tensordict: TensorDictBase,
        tensordict_out: TensorDictBase | None = None,
        **kwargs,
    ) -> TensorDictBase:
        """Writes ``action`` and the state keys into ``tensordict`` (or ``tensordict_out``)."""
        if "params" in kwargs or "vmap" in kwargs:
            raise ValueError("the discrete planners do not support functional calls.")
        out = tensordict if tensordict_out is None else tensordict_out
        action = self.planning(tensordict, _state_out=out)
        out.set(self.action_key, action)
        return out

    @torch.no_grad()
    def planning(
        self, td: TensorDictBase, _state_out: TensorDictBase | None = None
    ) -> torch.Tensor:
        """Plans (where needed) and returns the action, int64 ``[*B, 1]``.

        The state keys are written into ``td`` (or ``_state_out``) as a side effect.
        """
        batch = td.batch_size
        flat = td.reshape(-1) if td.batch_dims != 1 else td
        self._check_inputs(flat)
        flat = self._checked_frames(flat)
        rows = flat.batch_size[0]
        device = self.generator.device
        h = self.planning_horizon
        plan = self._read(flat, self.plan_key, (rows, h), torch.int64)
        cursor = self._read(flat, self.cursor_key, (rows, 1), torch.int64)
        length = self._read(flat, self.length_key, (rows, 1), torch.int64)
        score = self._read(flat, self.plan_cost_key, (rows, 1), torch.float32)
        valid = length.squeeze(-1) > 0
        is_init = flat.get("is_init", None)
        if is_init is not None:
            valid &= ~is_init.reshape(rows, -1).any(-1).to(device)
        if self.execution == "open_loop":
            need = ~valid | (cursor.squeeze(-1) >= length.squeeze(-1))
        else:
            need = torch.ones(rows, dtype=torch.bool, device=device)
        need &= ~finished_rows(flat).to(device)
        index = need.nonzero().squeeze(-1)
        if index.numel():
            sub = flat[index.to(flat.device)] if index.numel() < rows else flat
            new_plan, new_length, new_score = self._plan(
                sub, plan[index], cursor[index].squeeze(-1), valid[index]
            )
            plan[index] = new_plan
            length[index] = new_length.unsqueeze(-1)
            score[index] = new_score.unsqueeze(-1)
            cursor[index] = 0
        cursor = cursor.clamp_max(h - 1)
        action = plan.gather(-1, cursor)
        cursor = cursor + 1
        out = td if _state_out is None else _state_out
        for key, value in (
            (self.plan_key, plan),
            (self.cursor_key, cursor),
            (self.length_key, length),
            (self.plan_cost_key, score),
        ):
            out.set(key, value.reshape(*batch, value.shape[-1]).to(td.device))
        if self._action_shape == ():
            action = action.squeeze(-1)
        return action.reshape(*batch, *self._action_shape).to(td.device)

    # ------------------------------------------------------------------ #
    # Steps of a planning call
    # ------------------------------------------------------------------ #
    def _plan(
        self,
        td: TensorDictBase,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Plans rows ``td [b]``: (plan int64 ``[b, H]``, length ``[b]``, score ``[b]``)."""
        self._check_cost_keys(td)
        decisions, score, step = self._optimize(td, previous_plan, shift, valid)
        if self.prune:
            decisions, score, step = self._prune(td, decisions, score, step)
        plan = decisions.repeat_interleave(self.action_repeat, dim=-1)
        # Open loop stops at the best step for "min"; the whole sequence counts otherwise.
        if self.step_aggregation == "min":
            length = step + 1
        else:
            length = torch.full_like(step, self.planning_horizon)
        return plan, length, score

    def action_prior(self, td: TensorDictBase) -> torch.Tensor | None:
        """The rows' action distributions ``[b, A]`` under ``action_prior_key`` (``None``
        without one), checked and normalised; rows of ``td [b]`` being planned."""
        if self.action_prior_key is None:
            return None
        value = self._row_input(
            td,
            self.action_prior_key,
            "action_prior_key",
            "samples from",
            f"a distribution over the {self.num_actions} actions",
        ).to(self.generator.device, torch.float32)
        if value.shape[-1] != self.num_actions:
            raise ValueError(
                f"{self.action_prior_key!r} must hold {self.num_actions} action weights per "
                f"row, got {value.shape[-1]}."
            )
        total = value.sum(-1, keepdim=True)
        if (
            not bool(torch.isfinite(value).all())
            or bool((value < 0).any())
            or bool((total <= 0).any())
        ):
            raise ValueError(
                f"{self.action_prior_key!r} must hold finite, non-negative action weights "
                "with a positive sum in every row."
            )
        return value / total

    def excluded_actions(self, td: TensorDictBase) -> torch.Tensor | None:
        """bool ``[b, A]``: the actions the rows of ``td [b]`` may not start a plan with
        (``None`` without ``excluded_actions_key``, or when no row excludes any)."""
        if self.excluded_actions_key is None:
            return None
        value = self._row_input(
            td,
            self.excluded_actions_key,
            "excluded_actions_key",
            "reads the actions a plan may not start with from",
            f"bool [{self.num_actions}]",
        )
        if value.dtype is not torch.bool or value.shape[-1] != self.num_actions:
            raise ValueError(
                f"{self.excluded_actions_key!r} must hold bool [{self.num_actions}] per row "
                f"(True: the action may not start a plan), got {value.dtype} "
                f"{list(value.shape)} ([rows, values])."
            )
        value = value.to(self.generator.device)
        return value if bool(value.any()) else None

    def _row_input(
        self, td: TensorDictBase, key: NestedKey, argument: str, reads: str, holds: str
    ) -> torch.Tensor:
        """The per-row values ``[b, -1]`` under ``key`` (the planner's ``argument``)."""
        value = td.get(key, None)
        if value is None:
            raise MissingKeyError(
                f"{type(self).__name__} {reads} {key!r}, which the tensordict lacks: write "
                f"{holds} per row there (or build the planner with {argument}=None)."
            )
        return value.reshape(td.batch_size[0], -1)  # a tensordict entry leads with [b]

    def first_decision_probs(self, probs: torch.Tensor, excluded: torch.Tensor) -> torch.Tensor:
        """``probs [b, A]`` of a plan's first decision without the ``excluded [b, A]``
        actions, renormalised (rows excluding every action keep ``probs``)."""
        kept = probs.masked_fill(excluded, 0.0)
        total = kept.sum(-1, keepdim=True)
        return torch.where(total > 0, kept / total.clamp_min(1e-30), probs)

    def _optimize(
        self,
        td: TensorDictBase,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Best decisions int64 ``[b, H / r]``, their score ``[b]`` and best step ``[b]``."""
        raise NotImplementedError

    def _prune(
        self,
        td: TensorDictBase,
        decisions: torch.Tensor,
        score: torch.Tensor,
        step: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Drops decisions ``[b, D]`` one per round while that improves (score, step)."""
        d = self.num_decisions
        if d < 2:
            return decisions, score, step
        # variant j drops decision j and repeats the last decision at the end
        order = torch.arange(d, device=decisions.device)
        drop = torch.stack([torch.cat([order[:j], order[j + 1 :], order[-1:]]) for j in range(d)])
        active = torch.ones(decisions.shape[0], dtype=torch.bool, device=decisions.device)
        for _ in range(d - 1):
            index = active.nonzero().squeeze(-1)
            if not index.numel():
                break
            rows = td[index.to(td.device)] if index.numel() < td.batch_size[0] else td
            current = decisions[index]
            variants = current[:, drop]  # [b, D, D]
            new_score, new_step = self._evaluate(rows, variants)
            # only decisions up to the best step are dropped: the rest never runs
            last = step[index].div(self.action_repeat, rounding_mode="floor").unsqueeze(-1)
            new_score = torch.where(order <= last, new_score, torch.full_like(new_score, torch.inf))
            best = select_best(new_score, new_step)
            pick = torch.arange(index.numel(), device=best.device)
            cand_score, cand_step = new_score[pick, best], new_step[pick, best]
            better = improves(cand_score, cand_step, score[index], step[index])
            kept = index[better]
            decisions[kept] = variants[pick[better], best[better]]
            score[kept] = cand_score[better]
            step[kept] = cand_step[better]
            active[index[~better]] = False
        return decisions, score, step

    def _uniforms(self, rows: int, optim_steps: int) -> torch.Tensor:
        """Uniform numbers ``[rows, optim_steps, N, H / r]`` in one row-major draw."""
        shape = (rows, optim_steps, self.num_candidates, self.num_decisions)
        return torch.rand(shape, generator=self.generator, device=self.generator.device)

    def _evaluate(
        self, td: TensorDictBase, decisions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Scores candidates ``[b, N, H / r]``: (score ``[b, N]``, best step ``[b, N]``)."""
        rollout = self.imagine(td, decisions)
        out = score_rollout(self.cost, rollout)
        name = type(self.cost).__name__
        if not isinstance(out, TensorDictBase):
            raise ValueError(
                f"the cost {name} must return the rollout tensordict with its per-step cost "
                f"under cost_key={self.cost_key!r}, got a {type(out).__name__}."
            )
        per_step = out.get(self.cost_key, None)
        if per_step is None:
            raise ValueError(
                f"the cost {name} wrote no {self.cost_key!r} (cost_key) into the rollout; its "
                f"output holds {sorted(str(k) for k in out.keys(True, True))}."
            )
        expected = rollout.batch_size
        if per_step.shape != expected:
            raise ValueError(
                f"the cost {name} must write a per-step cost of shape {list(expected)} "
                f"([B, N, H]) under {self.cost_key!r}, got {list(per_step.shape)}."
            )
        score, step = aggregate_steps(per_step.to(torch.float32), self.step_aggregation)
        excluded = self.excluded_actions(td)
        if excluded is not None:  # candidates starting with an excluded action
            starts = excluded.gather(-1, decisions[..., 0].to(excluded.device))
            score = score.masked_fill(starts.to(score.device), torch.inf)
        return score, step

    def imagine(self, td: TensorDictBase, decisions: torch.Tensor) -> CandidateRollout:
        """Rolls candidate decisions ``[b, N, H / r]`` out from rows ``td [b]``.

        Returns the :class:`~dorp_rl.planners.CandidateRollout` ``[b, N, H]`` described
        in :mod:`dorp_rl.planners.costs`: ``action``, the ``("next", ...)`` keys the cost
        reads (all of them if it has no ``in_keys``) over the steps, and the root keys of
        ``td`` broadcast without copies. The env's ``imagine_candidates`` gives it where
        the env's class declares one (some values may stay lazy), else the env is
        stepped (module docstring).
        """
        rows, n = decisions.shape[:2]
        actions = decisions.repeat_interleave(self.action_repeat, dim=-1).to(td.device)
        if callable(getattr(type(self.env), "imagine_candidates", None)):
            next_keys = list(self._next_keys) if self._cost_keys else None
            imagined = self.env.imagine_candidates(td, actions, next_keys)
            if imagined is not None:
                rollout, lazy = imagined
                lazy = {unravel_key(k): v for k, v in lazy.items()}
                self._check_imagined(rollout, lazy, (rows, n, self.planning_horizon))
                return CandidateRollout(self._with_root(rollout, td), lazy)
        return CandidateRollout(self._with_root(self._step_candidates(td, actions), td))

    def _step_candidates(self, td: TensorDictBase, actions: torch.Tensor) -> TensorDictBase:
        """The rollout ``[b, N, H]`` of ``actions`` (per env step) by stepping the env."""
        rows, n = actions.shape[:2]
        current = td.select(*self._env_in_keys, strict=False).unsqueeze(1).expand(rows, n)
        outputs = []
        for t in range(self.planning_horizon):
            current = current.copy()
            current.set(
                self.action_key, actions[..., t : t + 1].reshape(rows, n, *self._action_shape)
            )
            current = self.env.step(current)
            next_td = current.get("next")
            if self._cost_keys:
                wanted = [k[1:] if len(k) > 2 else k[1] for k in self._next_keys]
                next_td = next_td.select(*wanted, strict=False)
            outputs.append(next_td)
            current = self.env.step_mdp(current)
        return TensorDict(
            {
                self.action_key: actions.unsqueeze(-1) if self._action_shape == (1,) else actions,
                "next": torch.stack(outputs, dim=2),
            },
            batch_size=[rows, n, self.planning_horizon],
            device=td.device,
        )

    # ------------------------------------------------------------------ #
    # Internals
    # ------------------------------------------------------------------ #
    def _with_root(self, rollout: TensorDictBase, td: TensorDictBase) -> TensorDictBase:
        """``rollout [b, N, H]`` with the root keys of the rows ``td [b]`` the cost reads
        (all of them if it has no ``in_keys``) broadcast over candidates and steps."""
        if self._cost_keys:
            root = td.select(*self._root_keys, strict=False)
        else:
            root = td.exclude("next", *self.state_keys)
        root = root.reshape(td.batch_size[0], 1, 1).expand(rollout.batch_size)
        rollout.update(root.exclude(self.action_key))
        return rollout

    def _check_imagined(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any], shape: tuple[int, ...]
    ) -> None:
        """Refuses an ``imagine_candidates`` result of the wrong shape or missing a key."""
        name = type(self.env).__name__
        if not isinstance(rollout, TensorDictBase) or tuple(rollout.batch_size) != shape:
            got = (
                list(rollout.batch_size)
                if isinstance(rollout, TensorDictBase)
                else type(rollout).__name__
            )
            raise ValueError(
                f"{name}.imagine_candidates must return a rollout of batch shape "
                f"{list(shape)} ([b, N, H]), got {got}."
            )
        present = set(rollout.keys(True, True)) | set(lazy)
        for key in [self.action_key, *self._next_keys]:
            if key not in present:
                raise ValueError(
                    f"{name}.imagine_candidates returned no {key!r} (neither in the rollout "
                    f"nor lazy), which the planner asked for; it holds "
                    f"{sorted(str(k) for k in present)}. Return None for keys it cannot "
                    "imagine, and the planner steps the env instead."
                )

    def _env_output_keys(self) -> list[NestedKey]:
        env = self.env
        keys: list[NestedKey] = []
        for spec in (env.full_observation_spec, env.full_reward_spec, env.full_done_spec):
            keys += list(spec.keys(True, True))
        return keys

    def _env_input_keys(self) -> list[NestedKey]:
        env = self.env
        keys = list(env.full_observation_spec.keys(True, True))
        keys += [k for k in env.full_state_spec.keys(True, True) if k not in keys]
        return keys

    def _check_inputs(self, flat: TensorDictBase) -> None:
        """Shapes of the acting rows against what the planning env takes (no device sync).

        A planning env of another world (e.g. 2 objects while 1 is acting) would
        otherwise fail deep inside its dynamics, or plan on a misread state.
        """
        specs = self.env.full_observation_spec.clone()
        specs.update(self.env.full_state_spec)
        for key in self._env_in_keys:
            value = flat.get(key, None)
            if not isinstance(value, torch.Tensor) or key not in specs.keys(True, True):
                continue
            expected = tuple(specs[key].shape)
            if tuple(value.shape[1:]) != expected:
                raise ValueError(
                    f"the acting tensordict's {key!r} has shape {list(value.shape[1:])} per "
                    f"row, but the planning env {type(self.env).__name__} takes "
                    f"{list(expected)}: it models another environment than the acting one "
                    "(e.g. another number of objects). Build the planning env from the "
                    "acting env."
                )

    def _find_frame_keys(self) -> list[NestedKey]:
        """Root keys read as frames: the planning env's uint8 image observations the
        planner reads, and the keys its cost declares (``root_frame_keys``: a goal image,
        the start frame)."""
        spec = self.env.full_observation_spec
        keys = [
            key
            for key in spec.keys(True, True)
            if key in self.in_keys and spec[key].dtype == torch.uint8 and len(spec[key].shape) >= 3
        ]
        modules = self.cost.modules() if isinstance(self.cost, nn.Module) else [self.cost]
        for module in modules:
            keys += [unravel_key(k) for k in getattr(module, "root_frame_keys", ())]
        return [k for k in dict.fromkeys(keys) if not (isinstance(k, tuple) and k[0] == "next")]

    def _checked_frames(self, flat: TensorDictBase) -> TensorDictBase:
        """The acting rows with their frames checked (:func:`~dorp_rl.frames.check_task_frames`
        against the planning env) and float frames in ``[0, 1]`` turned into uint8.

        Once per call, before any rollout: a goal image of another environment, an
        all-black or NaN frame, or float frames in 0..255 are refused instead of planned
        with. Converted frames go into a shallow copy (the caller's tensordict is left as
        given), so the costs and the planning env see uint8 frames whatever the input.
        """
        rows = flat.batch_size[0]
        converted = {}
        for key in self._frame_keys:
            value = flat.get(key, None)
            if not isinstance(value, torch.Tensor):
                continue
            frames = check_task_frames(value, str(key), self.env, lead=(rows,), spec_key=key)
            if frames is not value:
                converted[key] = frames.to(value.device)
        if not converted:
            return flat
        flat = flat.copy()
        for key, frames in converted.items():
            flat.set(key, frames)
        return flat

    def _check_cost_keys(self, td: TensorDictBase) -> None:
        present = set(td.keys(True, True))
        for key in self._root_keys:
            if key not in present:
                raise MissingRolloutKeyError(
                    f"the cost {type(self.cost).__name__} needs the key {key!r}, which is "
                    f"missing from the tensordict given to the planner (and so from the "
                    f"imagined rollout). Keys present: {sorted(str(k) for k in present)}."
                )

    def _read(
        self, td: TensorDictBase, key: str, shape: tuple[int, ...], dtype: torch.dtype
    ) -> torch.Tensor:
        value = td.get(key, None)
        device = self.generator.device
        if value is None:
            return torch.zeros(shape, dtype=dtype, device=device)
        if tuple(value.shape) != shape:
            raise ValueError(
                f"{key!r} must have shape {list(shape)} for this planner "
                f"(planning_horizon {self.planning_horizon}), got {list(value.shape)}; was it "
                "written by another planner?"
            )
        return value.to(device=device, dtype=dtype).clone()

    def extra_repr(self) -> str:
        return (
            f"planning_horizon={self.planning_horizon}, num_candidates={self.num_candidates}, "
            f"action_repeat={self.action_repeat}, execution={self.execution!r}, "
            f"step_aggregation={self.step_aggregation!r}, cost_key={self.cost_key!r}, "
            f"prune={self.prune}"
        )


def finished_rows(td: TensorDictBase) -> torch.Tensor:
    """Bool ``[rows]``: rows of a flat tensordict whose episode is over.

    A batched ``env.rollout`` keeps finished rows in its batch until every row is done:
    their root ``done`` is set, and with ``break_when_all_done`` torchrl also marks them
    ``_step=False`` (not stepped). Planning for them would be wasted.
    """
    rows = td.batch_size[0]
    finished = torch.zeros(rows, dtype=torch.bool)
    done = td.get("done", None)
    if done is not None:
        finished |= done.reshape(rows, -1).any(-1).cpu()
    stepping = td.get("_step", None)
    if stepping is not None:
        finished |= ~stepping.reshape(rows, -1).any(-1).cpu()
    return finished


def _cost_aggregation(cost: nn.Module, cost_key: NestedKey) -> str:
    """The ``step_aggregation`` of the module that writes ``cost_key`` (``"sum"`` if none says).

    A composed cost (a :class:`~tensordict.nn.TensorDictSequential` ending in a
    :class:`~dorp_rl.planners.WeightedCostSum`) has no attribute of its own: the module
    that writes the key the planner reads decides.
    """
    if hasattr(cost, "step_aggregation"):
        return cost.step_aggregation
    writer = None
    for module in cost.modules():
        keys = [unravel_key(k) for k in getattr(module, "out_keys", None) or []]
        if module is not cost and cost_key in keys and hasattr(module, "step_aggregation"):
            writer = module
    return writer.step_aggregation if writer is not None else "sum"


def aggregate_steps(
    per_step: torch.Tensor, step_aggregation: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Folds per-step costs ``[..., H]`` into (score ``[...]``, best step ``[...]``).

    ``step_aggregation`` says how the steps of one candidate make its score: ``"min"``,
    the lowest step cost and the first step reaching it; ``"sum"``, the total, step
    ``H - 1``; ``"final"``, the last step's cost, step ``H - 1``.

    Examples:
        >>> import torch
        >>> from dorp_rl.planners import aggregate_steps
        >>> per_step = torch.tensor([[3.0, 1.0, 1.0, 2.0]])
        >>> aggregate_steps(per_step, "min")
        (tensor([1.]), tensor([1]))
        >>> aggregate_steps(per_step, "sum")
        (tensor([7.]), tensor([3]))
    """
    check_step_aggregation(step_aggregation)
    last = per_step.shape[-1] - 1
    if step_aggregation == "min":
        score, step = per_step.min(dim=-1)
        return score, step
    full = torch.full(per_step.shape[:-1], last, dtype=torch.int64, device=per_step.device)
    if step_aggregation == "sum":
        return per_step.sum(-1), full
    return per_step[..., -1], full


def improves(
    score: torch.Tensor, step: torch.Tensor, best_score: torch.Tensor, best_step: torch.Tensor
) -> torch.Tensor:
    """Bool: a (score, step) beats the best so far: lower, or as low and earlier."""
    return (score < best_score) | ((score == best_score) & (step < best_step))


def select_best(score: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """Index ``[b]`` of the best candidate of each row: lowest score, then earliest step."""
    best = score.min(dim=-1, keepdim=True).values
    tied_step = torch.where(score <= best, step, torch.full_like(step, torch.iinfo(step.dtype).max))
    return tied_step.argmin(dim=-1)
