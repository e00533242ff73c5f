"""Assembles the DORP policy from an env, codes, a graph and a :class:`DORPConfig`."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tensordict import NestedKey
from torch import nn
from torchrl.envs import EnvBase

from dorp_rl.envs.spec import DiscreteActions, env_identity
from dorp_rl.planners.cem import CategoricalCEMPlanner
from dorp_rl.planners.code_graph import CodeGraph
from dorp_rl.planners.costs import (
    CodeMatchCost,
    CostSequence,
    FirstArrival,
    LatentGoalCost,
    ObjectMapCost,
    PixelDistanceCost,
    WeightedCostSum,
    check_step_penalty,
)
from dorp_rl.planners.random_shooting import RandomShootingPlanner
from dorp_rl.policies.abstract_goal import AbstractGoalPolicy
from dorp_rl.policies.config import DORPConfig
from dorp_rl.policies.low_level import TRUE_DYNAMICS, make_planning_env
from dorp_rl.policies.recovery import RecoveryRule, recovery_rules
from dorp_rl.policies.state import GOAL_PRIOR_KEY, NOOPS_KEY, PRIOR_KEY
from dorp_rl.validation import check_float, check_keywords, check_seed, derive_seed, keyword_names

__all__ = [
    "make_dorp_policy",
    "make_waypoint_cost",
]

_CEM_ONLY = frozenset(
    ("optim_steps", "top_k", "warm_start", "warm_start_mix", "smoothing", "min_probability")
)
_CONFIG_FIELDS = frozenset(f.name for f in dataclasses.fields(DORPConfig))
#: the goal term's blur widths when none are given: DORPConfig's, the one default
DEFAULT_GOAL_BLUR_SIGMAS = next(
    f.default for f in dataclasses.fields(DORPConfig) if f.name == "goal_blur_sigmas"
)


def make_waypoint_cost(
    encoder: nn.Module,
    *,
    waypoint_goal_weight: float = 0.0,
    step_penalty: float = 0.0,
    first_arrival: bool = False,
    goal_blur_sigmas: Sequence[float] | None = None,
    cache_size: int = 2**18,
    code_key: NestedKey | None = None,
    latent_model: Any = None,
) -> nn.Module:
    """The cost DORP's waypoint planner ranks its plans by (written under ``cost``).

    A :class:`~dorp_rl.planners.CodeMatchCost` on ``subgoal_code`` over the one-hots of
    ``subgoal_mask``; with ``waypoint_goal_weight > 0``, plus that weight times the goal
    image's blurred :class:`~dorp_rl.planners.PixelDistanceCost` (each folded over the
    plan's steps with ``min``), so that among plans reaching the waypoint those leaving
    the frame nearest the goal image win. ``step_penalty`` is the code term's cost per
    step of a matching frame (earlier arrival wins; see
    :class:`~dorp_rl.planners.CodeMatchCost`). ``first_arrival``: a plan is judged at
    the first step that reaches the waypoint, where the policy stops following it
    (:class:`~dorp_rl.planners.FirstArrival`), not at a later, better step that never
    runs. ``code_key``: the codes the planning env
    predicts (``("next", "code")`` of a latent world model), read instead of encoding
    predicted frames. ``latent_model``: the goal term is the distance of the imagined
    latents to the goal image's (:class:`~dorp_rl.planners.LatentGoalCost`) instead of
    the pixel distance, so that no frame is decoded. ``goal_blur_sigmas``: the goal
    term's blur widths (None: :class:`DORPConfig`'s default).

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.envs import OracleCodeEncoder
        >>> env = ObjectRearrangementEnv(num_objects=2)
        >>> cost = make_waypoint_cost(OracleCodeEncoder(env), waypoint_goal_weight=0.003)
        >>> type(cost).__name__
        'CostSequence'
    """
    waypoint_goal_weight = check_float("waypoint_goal_weight", waypoint_goal_weight, low=0.0)
    alone = waypoint_goal_weight == 0 and not first_arrival
    code_cost = CodeMatchCost(
        encoder,
        "subgoal_code",
        onehots="subgoal_mask",
        out_key="cost" if alone else "waypoint_code_cost",
        step_penalty=step_penalty,
        cache_size=cache_size,
        code_key=code_key,
    )
    if alone:
        return code_cost
    parts: list[nn.Module] = [code_cost]
    weights = {"waypoint_code_cost": 1.0}
    if waypoint_goal_weight > 0:
        if latent_model is not None:
            parts.append(LatentGoalCost(latent_model, out_key="waypoint_goal_cost"))
        else:
            sigmas = DEFAULT_GOAL_BLUR_SIGMAS if goal_blur_sigmas is None else goal_blur_sigmas
            parts.append(PixelDistanceCost(out_key="waypoint_goal_cost", blur_sigmas=sigmas))
        weights["waypoint_goal_cost"] = float(waypoint_goal_weight)
    total = "waypoint_cost" if first_arrival else "cost"
    parts.append(WeightedCostSum(weights, out_key=total, step_aggregation="min"))
    if first_arrival:
        parts.append(FirstArrival("waypoint_code_cost", cost_key=total, out_key="cost"))
    return CostSequence(*parts)


def make_goal_cost(
    encoder: nn.Module,
    *,
    goal_code_weight: float,
    goal_blur_sigmas: Sequence[float],
    goal_map_weight: float = 0.0,
    code_key: NestedKey | None = None,
    latent_model: Any = None,
    goal_latent_weight: float = 0.0,
) -> nn.Module:
    """The goal-image phase's cost: the goal's blurred pixel distance, plus (with
    ``goal_map_weight > 0``) the blurred distance of the encoder's object maps to the
    goal's, and (with ``goal_code_weight > 0``) a code term weighted per row by
    ``goal_code_weight`` (reading predicted codes under ``code_key`` when the planning
    env writes them).

    With ``goal_latent_weight > 0`` the distance of the imagined latents of
    ``latent_model`` to the goal image's (:class:`~dorp_rl.planners.LatentGoalCost`)
    takes the place of the pixel and object-map terms.

    The goal-image phase starts with every code at the goal's: frames that leave them
    cost more than any pixel distance, so the pixel cost cannot undo the plan.
    """
    goal_map_weight = check_float("goal_map_weight", goal_map_weight, low=0.0)
    goal_latent_weight = check_float("goal_latent_weight", goal_latent_weight, low=0.0)
    terms: list[nn.Module]
    weights: dict[str, float | str]
    if goal_latent_weight > 0:
        if latent_model is None:
            raise ValueError(
                "goal_latent_weight > 0 needs the latent model of a planning env that "
                "imagines latents (latent_model); pass goal_latent_weight=0."
            )
        terms = [LatentGoalCost(latent_model, out_key="goal_latent_cost")]
        weights = {"goal_latent_cost": goal_latent_weight}
        goal_map_weight = 0.0
    else:
        pixel_cost = PixelDistanceCost(out_key="pixel_cost", blur_sigmas=goal_blur_sigmas)
        if goal_code_weight == 0 and goal_map_weight == 0:
            return pixel_cost
        terms, weights = [pixel_cost], {"pixel_cost": 1.0}
    if goal_map_weight > 0:
        terms.append(ObjectMapCost(encoder, out_key="goal_map_cost", blur_sigmas=goal_blur_sigmas))
        weights["goal_map_cost"] = goal_map_weight
    if goal_code_weight > 0:
        terms.append(
            CodeMatchCost(encoder, "goal_code", out_key="goal_code_cost", code_key=code_key)
        )
        weights["goal_code_cost"] = "goal_code_weight"
    return CostSequence(*terms, WeightedCostSum(weights, step_aggregation="min"))


def make_dorp_policy(
    env: EnvBase,
    encoder: nn.Module | str | Path,
    graph: CodeGraph | str | Path,
    config: DORPConfig | None = None,
    *,
    low_level: str | EnvBase | nn.Module = "gt",
    seed: int | None = None,
    rules: Sequence[RecoveryRule] = (),
    **overrides: Any,
) -> AbstractGoalPolicy:
    """Assembles a DORP policy for ``env`` from checkpoints or objects.

    Args:
        env: the acting env (its dynamics serve as the oracle low level).
        encoder: an encoder, or the path of a representation checkpoint.
        graph: a :class:`~dorp_rl.planners.CodeGraph`, or the path of a saved one.
        config: the policy's settings; default :meth:`DORPConfig.for_env` of ``env``
            (the generic recipe with the ``dorp`` settings of the env's profile).
        low_level: ``"gt"`` (the env's true dynamics), a planning env
            (:class:`~dorp_rl.envs.VideoModelEnv`, ...), a video prediction model, or the
            path of a world-model checkpoint (:func:`~dorp_rl.policies.make_planning_env`).
        seed: seeds the planners (the goal planner with a derived seed).
        rules: recovery rules of your own (:class:`~dorp_rl.policies.RecoveryRule`),
            offered each decision before the ones ``config`` turns on.
        **overrides: :class:`DORPConfig` fields changed from ``config``, and more
            arguments of the planners (``optim_steps``, ``top_k``, ... of
            :class:`~dorp_rl.planners.CategoricalCEMPlanner`).

    Raises:
        ValueError: a graph built for another environment, encoder or code sizes, an
            unknown planner or low level, or a setting out of its range.

    Examples:
        >>> from dorp_rl.data import collect_play_data
        >>> from dorp_rl.envs import KeyWallEnv
        >>> from dorp_rl.envs import OracleCodeEncoder
        >>> from dorp_rl.planners import CodeGraph
        >>> env = KeyWallEnv(batch_size=(1,), seed=0)
        >>> oracle = OracleCodeEncoder(env, cell_size=4)
        >>> graph = CodeGraph.from_play_data(collect_play_data(env, 500, seed=0), oracle)
        >>> policy = make_dorp_policy(env, oracle, graph, num_candidates=64, seed=0)
        >>> policy.config.reenter, policy.config.num_candidates  # the key rooms' profile
        (True, 64)
    """
    from dorp_rl.trainers import load_encoder

    seed = check_seed(seed, optional=True)
    if not isinstance(env, EnvBase):
        raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
    fields = {k: v for k, v in overrides.items() if k in _CONFIG_FIELDS}
    planner_kwargs = {k: v for k, v in overrides.items() if k not in _CONFIG_FIELDS}
    # The planners' own keywords, less those set from the config.
    passed_on = (
        set(keyword_names(RandomShootingPlanner)) | set(keyword_names(CategoricalCEMPlanner))
    ) - {
        "env",
        "cost",
        "execution",
        "key_prefix",
        "seed",
        "prune",
        "excluded_actions_key",
        *_CONFIG_FIELDS,
    }
    check_keywords(planner_kwargs, passed_on, "make_dorp_policy (for its planners)")
    if config is None:
        config = DORPConfig.for_env(env, **fields)
    elif not isinstance(config, DORPConfig):
        raise ValueError(f"config must be a DORPConfig, got {type(config).__name__}.")
    else:
        config = config.replace(**fields)
    suited = DORPConfig.WHERE_SUITED  # what the fields left None take where they suit
    identity = env_identity(env)
    if isinstance(encoder, (str, Path)):
        encoder = load_encoder(encoder, env)
    if isinstance(graph, (str, Path)):
        graph = CodeGraph.load(graph, encoder=encoder, env_config=identity)
    elif graph.env_config is not None and graph.env_config != identity:
        stored, wanted = graph.env_config, identity
        diff = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
        details = "; ".join(f"{k}: graph {stored.get(k)!r}, env {wanted.get(k)!r}" for k in diff)
        raise ValueError(
            f"the code graph was built from another environment's play data ({details})."
        )
    planning_env = make_planning_env(env, low_level)
    code_key, waypoint_env = _predicted_codes(planning_env, encoder, config)
    kinds = {"rs": RandomShootingPlanner, "cem": CategoricalCEMPlanner}
    goal_kind = config.goal_planner or config.planner
    if config.action_persistence is not None and "rs" not in (config.planner, goal_kind):
        raise ValueError(
            "action_persistence is a RandomShootingPlanner argument, but neither planner is "
            "random shooting: pass planner='rs' (or goal_planner='rs') or drop it."
        )
    persistence = config.action_persistence
    rs_only = {
        "action_persistence": suited["action_persistence"] if persistence is None else persistence
    }
    shape = {
        "planning_horizon": config.planning_horizon,
        "num_candidates": config.num_candidates,
        "action_repeat": config.action_repeat,
        "execution": "open_loop",
        "prune": config.prune_plans,
    }
    # Arguments only CEM has go to the CEM planners; anything else both planners take.
    cem_only = {k: v for k, v in planner_kwargs.items() if k in _CEM_ONLY}
    shared = {k: v for k, v in planner_kwargs.items() if k not in _CEM_ONLY}
    if cem_only and "cem" not in (config.planner, goal_kind):
        raise ValueError(
            f"{sorted(cem_only)} are CategoricalCEMPlanner arguments, but neither planner is "
            "CEM: pass planner='cem' (or goal_planner='cem') or drop them."
        )
    if config.avoid_noops is None:  # the env's own dynamics never mispredict a move
        config = config.replace(
            avoid_noops=not (isinstance(low_level, str) and low_level == TRUE_DYNAMICS)
        )
    excluded = {"excluded_actions_key": NOOPS_KEY if config.avoid_noops else None}
    if config.action_prior_mix is None:
        mix = suited["action_prior_mix"] if graph.action_counts is not None else 0.0
        config = config.replace(action_prior_mix=mix)
    has_maps = callable(getattr(encoder, "object_maps", None))
    if config.goal_map_weight is None:
        config = config.replace(goal_map_weight=suited["goal_map_weight"] if has_maps else 0.0)
    if config.goal_action_prior_mix is None:
        suits = has_maps and graph.action_counts is not None
        goal_mix = suited["goal_action_prior_mix"] if suits else 0.0
        config = config.replace(goal_action_prior_mix=goal_mix)
    latent_model = getattr(planning_env, "latent_model", None)
    if config.goal_latent_weight is None:
        latent_weight = suited["goal_latent_weight"] if latent_model is not None else 0.0
        config = config.replace(goal_latent_weight=latent_weight)
    # The waypoint cost's goal term (a tie-break between plans reaching the waypoint) is
    # judged on imagined latents whenever there are any: a waypoint call decodes no frame.
    waypoint_cost = make_waypoint_cost(
        encoder,
        latent_model=latent_model,
        waypoint_goal_weight=config.waypoint_goal_weight,
        step_penalty=check_step_penalty(config.waypoint_step_penalty, "waypoint_step_penalty"),
        first_arrival=config.waypoint_first_arrival,
        goal_blur_sigmas=config.goal_blur_sigmas,
        code_key=code_key,
    )
    waypoint = kinds[config.planner](
        waypoint_env,
        waypoint_cost,
        **shape,
        seed=seed,
        key_prefix="waypoint_planner_",
        action_prior_key=PRIOR_KEY if config.action_prior_mix > 0 else None,
        **excluded,
        **shared,
        **(cem_only if config.planner == "cem" else rs_only),
    )
    goal_cost = make_goal_cost(
        encoder,
        goal_code_weight=config.goal_code_weight,
        goal_blur_sigmas=config.goal_blur_sigmas,
        goal_map_weight=config.goal_map_weight,
        code_key=code_key,
        latent_model=latent_model,
        goal_latent_weight=config.goal_latent_weight,
    )
    goal = kinds[goal_kind](
        planning_env,
        goal_cost,
        **shape,
        seed=None if seed is None else derive_seed(seed, 1),
        key_prefix="goal_planner_",
        action_prior_key=GOAL_PRIOR_KEY if config.goal_action_prior_mix > 0 else None,
        **excluded,
        **shared,
        **(cem_only if goal_kind == "cem" else rs_only),
    )
    own = list(rules)
    with_own = None
    if own:
        code_term = "goal_code_weight" in goal.in_keys
        with_own = [*own, *recovery_rules(config, goal_code_term=code_term)]
    return AbstractGoalPolicy(
        encoder, graph, waypoint, goal, config, rules=with_own, actions=DiscreteActions.of(env)
    )


def _predicted_codes(
    planning_env: EnvBase, encoder: nn.Module, config: DORPConfig
) -> tuple[NestedKey | None, EnvBase]:
    """Where the costs read the codes of imagined frames, and the waypoint planner's env.

    A planning env that predicts the encoder's codes declares a ``code`` observation (a
    latent world model): the costs read ``("next", "code")`` instead of encoding frames,
    and the waypoint planner, whose cost then needs no frames (without a goal-image term,
    or with one judged on the latents the env imagines), plans through its
    ``without_frames()`` variant if it has one. An env whose
    ``predicts_codes_of(encoder)`` says its codes are another encoder's is planned
    through its frames, which the costs encode.
    """
    spec = planning_env.observation_spec
    if "code" not in spec.keys():
        return None, planning_env
    learned_by = getattr(planning_env, "predicts_codes_of", None)
    if callable(learned_by) and not learned_by(encoder):
        return None, planning_env  # another encoder's codes: the costs encode frames
    predicted = int(spec["code"].shape[-1])
    if predicted != len(encoder.code_sizes):
        raise ValueError(
            f"the planning env predicts {predicted} codes per frame, the encoder has "
            f"{len(encoder.code_sizes)} one-hots (code_sizes {tuple(encoder.code_sizes)}): "
            "its world model was trained on another encoder's codes."
        )
    sizes = getattr(getattr(planning_env, "model", None), "code_sizes", None)
    if sizes is not None and tuple(sizes) != tuple(encoder.code_sizes):
        raise ValueError(
            f"the planning env's world model predicts codes of sizes {tuple(sizes)}, the "
            f"encoder has {tuple(encoder.code_sizes)}: train it on this encoder's codes."
        )
    waypoint_env = planning_env
    lighter = getattr(planning_env, "without_frames", None)
    on_latents = getattr(planning_env, "latent_model", None) is not None
    if (config.waypoint_goal_weight == 0 or on_latents) and callable(lighter):
        waypoint_env = lighter()
    return ("next", "code"), waypoint_env
