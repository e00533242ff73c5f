"""Discrete model-predictive planners: random shooting and categorical CEM.

Both are :class:`torchrl.modules.planners.MPCPlannerBase` subclasses for a
:class:`~torchrl.data.Categorical` action: given the acting envs' tensordict (batch
``[B]``), they sample ``N`` candidate action sequences per row, roll them out in a
planning env (:class:`~dorp_rl.envs.GroundTruthModelEnv`,
:class:`~dorp_rl.envs.WorldModelEnv`, or any non-batch-locked env) on a ``[B, N]``
batch, score them with a cost module (:mod:`dorp_rl.planners.costs`) and write an
``action``. torchrl's own ``CEMPlanner`` / ``MPPIPlanner`` assume continuous actions.

Horizon and action repeat
    ``horizon`` counts env steps. With ``action_repeat = r`` a candidate is
    ``horizon / r`` decisions, each repeated ``r`` times (the authors' 7 actions x 2 =
    14 steps); ``r`` must divide ``horizon``.

Scoring
    The cost gives a per-step cost ``[B, N, H]``; ``reduction`` (by default the cost's
    own ``reduction`` attribute, else ``"sum"``) folds it into one score per candidate:
    ``"sum"``, ``"final"`` (last step) or ``"min"`` (best step; among equal scores the
    candidate that gets there earliest wins).

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
episode never follows the previous episode's plan.

Randomness
    A ``torch.Generator`` owned by the planner, seeded by ``seed`` (or by torch's global
    generator when ``seed=None``); :meth:`set_seed` reseeds it. The same seed and the
    same inputs give the same plans. Uniform numbers are drawn in one row-major block per
    call (``[B, iterations, N, H / r]``), so a row's candidates do not depend on the rows
    after it (row 0 planned alone or first in a batch sees the same samples), and no
    computation mixes rows: one row's goal never changes another row's plan.
"""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, unravel_key
from torch import nn
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TensorDictPrimer
from torchrl.modules.planners import MPCPlannerBase

from dorp_rl.planners.costs import MissingRolloutKeyError, check_reduction

EXECUTIONS = ("receding", "open_loop")


class DiscreteMPCPlanner(MPCPlannerBase):
    """Shared machinery of the discrete planners (sampling, rollouts, scoring, state).

    Subclasses implement :meth:`_optimize`. See the module docstring for the keys,
    execution modes and randomness.

    Args:
        env: the planning env (not batch-locked, Categorical action).
        cost: a cost module (``forward(rollout [B, N, H]) -> [B, N, H]``), ideally with
            ``in_keys`` and ``reduction`` attributes (:mod:`dorp_rl.planners.costs`).
        num_candidates: sequences per row and per iteration (``N``).
        horizon: env steps per sequence (``H``).
        action_repeat: env steps per decision; must divide ``horizon``.
        execution: ``"receding"`` or ``"open_loop"``.
        reduction: ``"min"``, ``"sum"`` or ``"final"``; ``None`` takes the cost's.
        seed: seeds the planner's generator (``None``: drawn from torch's global one).
        action_key: where the action is written.
        key_prefix: prefix of the state keys.
    """

    def __init__(
        self,
        env: EnvBase,
        cost: nn.Module,
        *,
        num_candidates: int = 1000,
        horizon: int = 14,
        action_repeat: int = 1,
        execution: str = "receding",
        reduction: str | None = None,
        seed: int | None = None,
        action_key: NestedKey = "action",
        key_prefix: str = "planner_",
    ) -> None:
        if not isinstance(env, EnvBase):
            raise ValueError(f"env must be a torchrl EnvBase, got {type(env).__name__}.")
        if env.batch_locked:
            raise ValueError(
                f"the planning env {type(env).__name__} is batch-locked (batch_locked=True, "
                f"batch_size={tuple(env.batch_size)}): a planner steps a [B, N] batch of "
                "candidates in it, so it must accept any leading shape. Build it with "
                "batch_size=() and batch_locked=False, or wrap the env's dynamics in "
                "dorp_rl.envs.GroundTruthModelEnv / WorldModelEnv."
            )
        for name, value in (("num_candidates", num_candidates), ("horizon", horizon)):
            if int(value) != value or int(value) < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value}.")
        if int(action_repeat) != action_repeat or int(action_repeat) < 1:
            raise ValueError(f"action_repeat must be an integer >= 1, got {action_repeat}.")
        if int(horizon) % int(action_repeat):
            raise ValueError(
                f"action_repeat must divide horizon (horizon counts env steps: {horizon} steps "
                f"= horizon / action_repeat decisions each repeated action_repeat times), got "
                f"horizon={horizon} and action_repeat={action_repeat}."
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
        super().__init__(env, action_key=action_key)
        self.action_key = unravel_key(action_key)
        self.cost = cost
        self.num_actions = int(action_spec.n)
        self.num_candidates = int(num_candidates)
        self.horizon = int(horizon)
        self.action_repeat = int(action_repeat)
        self.num_decisions = self.horizon // self.action_repeat
        self.execution = execution
        self.reduction = check_reduction(
            reduction if reduction is not None else getattr(cost, "reduction", "sum")
        )
        self._action_shape = tuple(action_spec.shape)
        self.plan_key = f"{key_prefix}plan"
        self.cursor_key = f"{key_prefix}cursor"
        self.length_key = f"{key_prefix}length"
        self.cost_key = f"{key_prefix}cost"
        self.state_keys = [self.plan_key, self.cursor_key, self.length_key, self.cost_key]
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
        self.in_keys = list(dict.fromkeys([*self._env_in_keys, *self._root_keys, *self.state_keys]))
        self.out_keys = [self.action_key, *self.state_keys]
        self.generator = torch.Generator(device=env.device)
        self.set_seed(seed)

    # ------------------------------------------------------------------ #
    # Public helpers
    # ------------------------------------------------------------------ #
    def set_seed(self, seed: int | None) -> None:
        """Reseeds the planner's generator (``None``: a seed from torch's global generator)."""
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.generator.manual_seed(int(seed) % (2**63))

    def make_primer(self) -> TensorDictPrimer:
        """A :class:`~torchrl.envs.TensorDictPrimer` declaring the state keys (zeros at reset).

        Append it to the acting env (``env.append_transform(planner.make_primer())``)
        when a collector drives the planner; ``Collector(...,
        auto_register_policy_transforms=True)`` does it through
        :meth:`make_tensordict_primer`.
        """
        specs = Composite(
            {
                self.plan_key: Categorical(self.num_actions, shape=(self.horizon,)),
                self.cursor_key: Unbounded(shape=(1,), dtype=torch.int64),
                self.length_key: Unbounded(shape=(1,), dtype=torch.int64),
                self.cost_key: Unbounded(shape=(1,), dtype=torch.float32),
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
        rows = flat.batch_size[0]
        device = self.generator.device
        h = self.horizon
        plan = self._read(flat, self.plan_key, (rows, h), torch.int64)
        cursor = self._read(flat, self.cursor_key, (rows, 1), torch.int64)
        length = self._read(flat, self.length_key, (rows, 1), torch.int64)
        score = self._read(flat, self.cost_key, (rows, 1), torch.float32)
        valid = length.squeeze(-1) > 0
        is_init = flat.get("is_init", None)
        if is_init is not None:
            valid &= ~is_init.reshape(rows, -1).any(-1).to(device)
        if self.execution == "open_loop":
            need = ~valid | (cursor.squeeze(-1) >= length.squeeze(-1))
        else:
            need = torch.ones(rows, dtype=torch.bool, device=device)
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
            (self.cost_key, score),
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
        plan = decisions.repeat_interleave(self.action_repeat, dim=-1)
        # Open loop stops at the best step for "min"; the whole sequence counts otherwise.
        length = step + 1 if self.reduction == "min" else torch.full_like(step, self.horizon)
        return plan, length, score

    def _optimize(
        self,
        td: TensorDictBase,
        previous_plan: torch.Tensor,
        shift: torch.Tensor,
        valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Best decisions int64 ``[b, H / r]``, their score ``[b]`` and best step ``[b]``."""
        raise NotImplementedError

    def _uniforms(self, rows: int, iterations: int) -> torch.Tensor:
        """Uniform numbers ``[rows, iterations, N, H / r]`` in one row-major draw."""
        shape = (rows, iterations, self.num_candidates, self.num_decisions)
        return torch.rand(shape, generator=self.generator, device=self.generator.device)

    def _evaluate(
        self, td: TensorDictBase, decisions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Scores candidates ``[b, N, H / r]``: (score ``[b, N]``, best step ``[b, N]``)."""
        rollout = self.imagine(td, decisions)
        per_step = self.cost(rollout)
        expected = rollout.batch_size
        if not isinstance(per_step, torch.Tensor) or per_step.shape != expected:
            got = list(per_step.shape) if isinstance(per_step, torch.Tensor) else type(per_step)
            raise ValueError(
                f"the cost must return a per-step cost of shape {list(expected)} "
                f"([B, N, H]), got {got}."
            )
        return reduce_steps(per_step.to(torch.float32), self.reduction)

    def imagine(self, td: TensorDictBase, decisions: torch.Tensor) -> TensorDictBase:
        """Rolls candidate decisions ``[b, N, H / r]`` out from rows ``td [b]``.

        Returns the rollout tensordict ``[b, N, H]`` described in
        :mod:`dorp_rl.planners.costs`: ``action``, the ``("next", ...)`` keys the cost
        reads (all of them if it has no ``in_keys``) stacked over steps, and the root
        keys of ``td`` broadcast without copies.
        """
        rows, n = decisions.shape[:2]
        actions = decisions.repeat_interleave(self.action_repeat, dim=-1).to(td.device)
        current = td.select(*self._env_in_keys, strict=False).unsqueeze(1).expand(rows, n)
        outputs = []
        for t in range(self.horizon):
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
        horizon_shape = torch.Size([rows, n, self.horizon])
        if self._cost_keys:
            root = td.select(*self._root_keys, strict=False)
        else:
            root = td.exclude("next", *self.state_keys)
        root = root.reshape(rows, 1, 1).expand(horizon_shape)
        rollout = TensorDict(
            {
                self.action_key: actions.unsqueeze(-1) if self._action_shape == (1,) else actions,
                "next": torch.stack(outputs, dim=2),
            },
            batch_size=horizon_shape,
            device=td.device,
        )
        rollout.update(root.exclude(self.action_key))
        return rollout

    # ------------------------------------------------------------------ #
    # Internals
    # ------------------------------------------------------------------ #
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
                f"{key!r} must have shape {list(shape)} for this planner (horizon "
                f"{self.horizon}), got {list(value.shape)}; was it written by another planner?"
            )
        return value.to(device=device, dtype=dtype).clone()

    def extra_repr(self) -> str:
        return (
            f"num_candidates={self.num_candidates}, horizon={self.horizon}, "
            f"action_repeat={self.action_repeat}, execution={self.execution!r}, "
            f"reduction={self.reduction!r}"
        )


def reduce_steps(per_step: torch.Tensor, reduction: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Folds per-step costs ``[..., H]`` into (score ``[...]``, best step ``[...]``).

    ``"min"``: the lowest step cost and its first step; ``"sum"``: the total, step
    ``H - 1``; ``"final"``: the last step's cost, step ``H - 1``.
    """
    last = per_step.shape[-1] - 1
    if reduction == "min":
        return per_step.min(dim=-1)
    full = torch.full(per_step.shape[:-1], last, dtype=torch.int64, device=per_step.device)
    if reduction == "sum":
        return per_step.sum(-1), full
    if reduction == "final":
        return per_step[..., -1], full
    raise ValueError(f"unknown reduction {reduction!r}.")


def select_best(score: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """Index ``[b]`` of the best candidate of each row: lowest score, then earliest step."""
    best = score.min(dim=-1, keepdim=True).values
    tied_step = torch.where(score <= best, step, torch.full_like(step, torch.iinfo(step.dtype).max))
    return tied_step.argmin(dim=-1)


class RandomShootingPlanner(DiscreteMPCPlanner):
    """Random shooting: N uniformly random action sequences, keep the best.

    The paper's VF-RS draws 1000 sequences and executes the best one open loop.

    Args:
        env: the planning env (not batch-locked, Categorical action).
        cost: a cost module over the rollout (:mod:`dorp_rl.planners.costs`).
        num_candidates: sequences per row (default 1000).
        horizon: env steps per sequence (default 14).
        action_repeat: env steps per decision; must divide ``horizon``.
        execution: ``"receding"`` (default) or ``"open_loop"``.
        seed: seeds the planner's generator.
        reduction: ``"min"``, ``"sum"`` or ``"final"``; ``None`` takes the cost's.
        **kwargs: ``action_key``, ``key_prefix`` (see :class:`DiscreteMPCPlanner`).

    Examples:
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.planners import PixelDistanceCost, RandomShootingPlanner
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> planner = RandomShootingPlanner(
        ...     GroundTruthModelEnv(env), PixelDistanceCost(), num_candidates=100, horizon=6, seed=0
        ... )
        >>> td = env.rollout(3, planner)
        >>> td["action"].shape, td["planner_plan"].shape
        (torch.Size([2, 3, 1]), torch.Size([2, 3, 6]))
    """

    def __init__(
        self,
        env: EnvBase,
        cost: nn.Module,
        num_candidates: int = 1000,
        horizon: int = 14,
        action_repeat: int = 1,
        execution: str = "receding",
        seed: int | None = None,
        *,
        reduction: str | None = None,
        **kwargs,
    ) -> None:
        super().__init__(
            env,
            cost,
            num_candidates=num_candidates,
            horizon=horizon,
            action_repeat=action_repeat,
            execution=execution,
            reduction=reduction,
            seed=seed,
            **kwargs,
        )

    def _optimize(self, td, previous_plan, shift, valid):
        rows = td.batch_size[0]
        u = self._uniforms(rows, 1)[:, 0]
        decisions = (u * self.num_actions).floor().to(torch.int64).clamp_max(self.num_actions - 1)
        score, step = self._evaluate(td, decisions)
        best = select_best(score, step)
        index = torch.arange(rows, device=best.device)
        return decisions[index, best], score[index, best], step[index, best]


class CategoricalCEMPlanner(DiscreteMPCPlanner):
    """Cross-entropy method over per-step categorical distributions.

    Each iteration samples ``N`` sequences from independent per-decision categorical
    distributions ``[b, H / r, A]`` (uniform at first), scores them, and refits each
    distribution to the action frequencies of the elites (the ``elite_fraction`` best
    sequences), optionally smoothed with the previous distribution and floored at
    ``min_probability`` so that no action becomes impossible. The best sequence seen
    in any iteration is the plan. The paper's VF-CEM: 1000 samples, top 2 %,
    3 iterations.

    Warm start (``warm_start=True``): a row that has a plan from an earlier call starts
    from it shifted by the steps executed since (padded with its last action), as
    ``warm_start_mix * one_hot(shifted plan) + (1 - warm_start_mix) * uniform``.

    Args:
        env: the planning env (not batch-locked, Categorical action).
        cost: a cost module over the rollout (:mod:`dorp_rl.planners.costs`).
        num_candidates: sequences per row and iteration (default 1000).
        horizon: env steps per sequence (default 14).
        action_repeat: env steps per decision; must divide ``horizon``.
        num_iterations: CEM iterations (default 3).
        elite_fraction: fraction of candidates kept as elites, in ``(0, 1]``
            (default 0.02; at least one elite).
        warm_start: start from the previous plan shifted (see above).
        execution: ``"receding"`` (default) or ``"open_loop"``.
        smoothing: weight of the old distribution in each refit, in [0, 1).
        warm_start_mix: weight of the shifted plan in the initial distribution, in [0, 1].
        min_probability: floor of every action probability after a refit.
        reduction: ``"min"``, ``"sum"`` or ``"final"``; ``None`` takes the cost's.
        seed: seeds the planner's generator.
        **kwargs: ``action_key``, ``key_prefix`` (see :class:`DiscreteMPCPlanner`).

    Examples:
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.planners import CategoricalCEMPlanner, PixelDistanceCost
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> planner = CategoricalCEMPlanner(
        ...     GroundTruthModelEnv(env), PixelDistanceCost(), num_candidates=100, horizon=6,
        ...     elite_fraction=0.1, seed=0,
        ... )
        >>> td = env.rollout(3, planner)
        >>> td["action"].shape, bool(((td["action"] >= 0) & (td["action"] < 4)).all())
        (torch.Size([2, 3, 1]), True)
    """

    def __init__(
        self,
        env: EnvBase,
        cost: nn.Module,
        num_candidates: int = 1000,
        horizon: int = 14,
        action_repeat: int = 1,
        num_iterations: int = 3,
        elite_fraction: float = 0.02,
        warm_start: bool = True,
        execution: str = "receding",
        smoothing: float = 0.0,
        *,
        warm_start_mix: float = 0.5,
        min_probability: float = 1e-3,
        reduction: str | None = None,
        seed: int | None = None,
        **kwargs,
    ) -> None:
        if int(num_iterations) != num_iterations or int(num_iterations) < 1:
            raise ValueError(f"num_iterations must be an integer >= 1, got {num_iterations}.")
        if not 0.0 < float(elite_fraction) <= 1.0:
            raise ValueError(f"elite_fraction must be in (0, 1], got {elite_fraction}.")
        if not 0.0 <= float(warm_start_mix) <= 1.0:
            raise ValueError(f"warm_start_mix must be in [0, 1], got {warm_start_mix}.")
        if not 0.0 <= float(smoothing) < 1.0:
            raise ValueError(f"smoothing must be in [0, 1), got {smoothing}.")
        super().__init__(
            env,
            cost,
            num_candidates=num_candidates,
            horizon=horizon,
            action_repeat=action_repeat,
            execution=execution,
            reduction=reduction,
            seed=seed,
            **kwargs,
        )
        if not 0.0 <= float(min_probability) <= 1.0 / self.num_actions:
            raise ValueError(
                f"min_probability must be in [0, 1 / num_actions = {1.0 / self.num_actions}], "
                f"got {min_probability}."
            )
        self.num_iterations = int(num_iterations)
        self.elite_fraction = float(elite_fraction)
        self.num_elites = max(1, int(round(self.elite_fraction * self.num_candidates)))
        self.warm_start = bool(warm_start)
        self.warm_start_mix = float(warm_start_mix)
        self.smoothing = float(smoothing)
        self.min_probability = float(min_probability)

    def initial_probs(
        self, previous_plan: torch.Tensor, shift: torch.Tensor, valid: torch.Tensor
    ) -> torch.Tensor:
        """Initial per-decision distributions ``[b, H / r, A]`` (uniform, or warm-started).

        Args:
            previous_plan: int64 ``[b, H]``, the stored plans (per env step).
            shift: int64 ``[b]``, env steps executed since each was planned.
            valid: bool ``[b]``, which rows have a plan.
        """
        rows = previous_plan.shape[0]
        a, h = self.num_actions, self.horizon
        device = previous_plan.device
        uniform = torch.full((rows, self.num_decisions, a), 1.0 / a, device=device)
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
        cdf = probs.cumsum(-1).unsqueeze(1)  # [b, 1, D, A]
        index = (u.unsqueeze(-1) >= cdf).sum(-1)
        return index.clamp_max(self.num_actions - 1)

    def _refit(self, probs: torch.Tensor, elites: torch.Tensor) -> torch.Tensor:
        freq = torch.nn.functional.one_hot(elites, self.num_actions).to(probs.dtype).mean(1)
        probs = self.smoothing * probs + (1.0 - self.smoothing) * freq
        probs = probs.clamp_min(self.min_probability)
        return probs / probs.sum(-1, keepdim=True)

    def _optimize(self, td, previous_plan, shift, valid):
        rows = td.batch_size[0]
        probs = self.initial_probs(previous_plan, shift, valid)
        u = self._uniforms(rows, self.num_iterations)
        index = torch.arange(rows, device=probs.device)
        best_decisions = best_score = best_step = None
        for i in range(self.num_iterations):
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
                better = (cand_score < best_score) | (
                    (cand_score == best_score) & (cand_step < best_step)
                )
                best_decisions = torch.where(better.unsqueeze(-1), cand_decisions, best_decisions)
                best_score = torch.where(better, cand_score, best_score)
                best_step = torch.where(better, cand_step, best_step)
            if i + 1 < self.num_iterations:
                elite_index = score.topk(self.num_elites, dim=-1, largest=False).indices
                elites = decisions.gather(
                    1, elite_index.unsqueeze(-1).expand(-1, -1, self.num_decisions)
                )
                probs = self._refit(probs, elites)
        return best_decisions, best_score, best_step

    def extra_repr(self) -> str:
        return (
            f"{super().extra_repr()}, num_iterations={self.num_iterations}, "
            f"num_elites={self.num_elites}, warm_start={self.warm_start}"
        )
