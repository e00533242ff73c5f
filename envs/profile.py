"""Env profiles: everything the pipeline needs to know about one environment, in one place.

A profile names an environment and says how to build it, which code and world-model
presets suit it, which DORP settings, how its tasks are drawn and what their lower bound
is. The trainers, the evaluation and the ``dorp`` command read an env only through its
profile (and its specs), so a new env needs a profile next to it and no edit inside the
library. The project's own envs are declared exactly this way (in their modules).

A profile is found by :func:`env_profile`: a registered name (``"rearrangement"``) or an
import path ``"package.module:attribute"`` whose attribute is an :class:`EnvProfile` or a
function that builds a TorchRL env (it then gets a profile with the generic defaults).
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

__all__ = [
    "CodeDiagnostics",
    "EnvProfile",
    "env_profile",
    "profile_of",
    "register_env_profile",
    "registered_profiles",
    "reset_tasks",
]

#: rounds of redrawing tasks whose start is already their goal
_REDRAW_ROUNDS = 100


def reset_tasks(env: EnvBase, num_tasks: int, seed: int) -> TensorDict:
    """Tasks as the env's own reset draws them: ``state`` and ``goal_state`` of
    ``env.reset()`` after ``env.set_seed(seed)``, redrawn where a start equals its goal.

    The default task drawing of a profile. ``env`` must write ``state`` and
    ``goal_state`` on reset; its batch may be any size (rows are drawn until there are
    ``num_tasks``).

    Raises:
        ValueError: the env's reset writes no ``state`` / ``goal_state``, or every
            draw puts the goal at the start.
    """
    env.set_seed(int(seed))
    starts: list[torch.Tensor] = []
    goals: list[torch.Tensor] = []
    have = 0
    for _ in range(_REDRAW_ROUNDS + num_tasks):
        td = env.reset()
        missing = [k for k in ("state", "goal_state") if k not in td.keys()]
        if missing:
            raise ValueError(
                f"{type(env).__name__}'s reset writes no {missing}: tasks are drawn as "
                "(state, goal_state) pairs; give the profile a draw_tasks function."
            )
        state = td["state"].reshape(-1, *td["state"].shape[td.batch_dims :])
        goal = td["goal_state"].reshape(-1, *td["goal_state"].shape[td.batch_dims :])
        differ = (state != goal).flatten(1).any(-1)
        starts.append(state[differ].cpu())
        goals.append(goal[differ].cpu())
        have += int(differ.sum())
        if have >= num_tasks:
            break
    else:
        raise ValueError(
            f"{type(env).__name__}'s reset put the goal at the start in every draw; no tasks."
        )
    shape = torch.Size([num_tasks])
    return TensorDict(
        state=torch.cat(starts)[:num_tasks].to(torch.int64),
        goal_state=torch.cat(goals)[:num_tasks].to(torch.int64),
        batch_size=shape,
    )


@dataclass(frozen=True)
class CodeDiagnostics:
    """An env's own diagnostics of codes against its true states (:attr:`EnvProfile.diagnostics`).

    ``encode`` is ``encode(uint8 [n, C, H, W]) -> int64 [n, K]``, one code index per
    one-hot (an encoder's ``encode``).

    Attributes:
        measure: ``(env, encode, num_samples, seed) -> dict``: JSON-serialisable figures
            with at least ``num_onehots``; the code trainer logs them as it evaluates.
        pictures: ``(env, encode, out_dir, result) -> {name: path}``: the PNGs drawn from
            ``result`` (what ``measure`` returned) into ``out_dir``; ``None``: none.
        waypoint_maps: ``(env, encode, result) -> maps``: per one-hot code maps for the
            rollout GIFs (:func:`~dorp_rl.viz.rollouts.code_maps_for_waypoints` takes them);
            ``None``: the GIFs show codes as numbers only.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import CodeDiagnostics
        >>> def measure(env, encode, num_samples, seed):
        ...     codes = encode(env.reset()["pixels"])
        ...     return {"num_onehots": codes.shape[-1], "codes_used": len(codes.unique())}
        >>> diagnostics = CodeDiagnostics(measure)
    """

    measure: Callable[[EnvBase, Callable, int, int], Mapping[str, Any]]
    pictures: Callable[[EnvBase, Callable, Path, Mapping[str, Any]], dict[str, Path]] | None = None
    waypoint_maps: Callable[[EnvBase, Callable, Mapping[str, Any]], Any] | None = None

    def __post_init__(self) -> None:
        for name in ("measure", "pictures", "waypoint_maps"):
            value = getattr(self, name)
            if not callable(value) and not (value is None and name != "measure"):
                raise ValueError(
                    f"CodeDiagnostics.{name} must be a function, got {type(value).__name__}."
                )


@dataclass(frozen=True)
class EnvProfile:
    """One environment as the pipeline sees it: its name, factory, presets and task rules.

    Attributes:
        name: the registered name (``--env <name>``), or the import path it was loaded by.
        make_env: builds the env; called with ``batch_size``, ``device``, ``seed`` (and
            ``num_objects`` when :attr:`counts_objects`) as keywords.
        counts_objects: whether ``make_env`` takes ``num_objects``; otherwise a config's
            ``num_objects`` must be 1.
        default_num_objects: objects when a config does not say.
        env_type: the class of the env ``make_env`` builds, so :func:`profile_of` finds
            the profile of an env object (``None``: only found by name).
        play_trajectory_length: steps of each random play trajectory (``None``: chosen
            from the env's resets, :func:`~dorp_rl.data.choose_play_length`: 1 when
            they start in varied frames, else random walks of 100 steps).
        max_steps: step limit of a task, or a function of ``num_objects`` (``None``: the
            env's ``max_steps`` attribute, else 200).
        code_layout: one-hot sizes of the codes from one number and ``num_objects``
            (``encoder.code_sizes=(16,)`` in a config then means this layout); ``None``:
            a config's ``code_sizes`` are used as they are.
        codes: overrides of :class:`~dorp_rl.trainers.RepresentationConfig` that suit
            the env, a function of ``num_objects``.
        world_model: overrides of :class:`~dorp_rl.trainers.WorldModelConfig`, likewise.
        latent_model: overrides of :class:`~dorp_rl.trainers.LatentWorldModelConfig`,
            likewise (its play windows default to the world model's).
        groups: the code graph's groups (``"auto"``: read from the play data's codes,
            :func:`~dorp_rl.planners.coupled_groups`; ``"onehot"``, ``"full"`` or tuples
            of one-hot indices), a value or a function of ``num_objects``.
        graph_completion: whether the pipeline completes the code graphs of groups of
            several one-hots (:meth:`~dorp_rl.planners.CodeGraph.completed`): true when
            the one-hots of a group are objects that move independently (blocks), false
            when they change together (an agent and the key it carries). Never applied
            to the full-graph ablation (``groups="full"``).
        dorp: fields of :class:`~dorp_rl.policies.DORPConfig` that suit the env (e.g.
            ``reenter``, ``replan_on_miss``, ``waypoint_goal_weight``), over its defaults
            (:meth:`~dorp_rl.policies.DORPConfig.for_env`); a mapping, or a function of
            ``num_objects``.
        draw_tasks: ``(env, num_tasks, seed) -> TensorDict`` of ``state`` and
            ``goal_state`` (default :func:`reset_tasks`).
        lower_bound: ``(env, state, goal_state) -> [num_tasks]`` steps no policy can beat
            (``None``: unknown; results then report no bound).
        objects: ``state [N, ...] -> int [N, K]``, a position id per object (equal ids,
            same place): the labels of the ground-truth code diagnostics
            (:func:`~dorp_rl.eval.object_diagnostics`: selectivity and purity per
            one-hot); ``None``: label-free diagnostics only.
        diagnostics: the env's own code diagnostics over its true states
            (:class:`CodeDiagnostics`: figures, pictures, code maps for the GIFs), beside
            or instead of ``objects``; ``None``: none.
        description: one line for listings and messages.

    Examples:
        >>> from dorp_rl.envs import env_profile
        >>> profile = env_profile("rearrangement")
        >>> env = profile.build(num_objects=2, batch_size=(3,))
        >>> type(env).__name__, profile.code_sizes((16,), 2), profile.task_limit(2)
        ('ObjectRearrangementEnv', (16, 16), 400)
    """

    name: str
    make_env: Callable[..., EnvBase]
    counts_objects: bool = False
    default_num_objects: int = 1
    env_type: type | None = None
    play_trajectory_length: int | None = None
    max_steps: int | Callable[[int], int] | None = None
    code_layout: Callable[[int, int], tuple[int, ...]] | None = None
    codes: Callable[[int], Mapping[str, Any]] | None = None
    world_model: Callable[[int], Mapping[str, Any]] | None = None
    latent_model: Callable[[int], Mapping[str, Any]] | None = None
    groups: Any = "auto"
    graph_completion: bool = False
    dorp: Mapping[str, Any] | Callable[[int], Mapping[str, Any]] = field(default_factory=dict)
    draw_tasks: Callable[[EnvBase, int, int], TensorDictBase] | None = None
    lower_bound: Callable[[EnvBase, torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    objects: Callable[[torch.Tensor], torch.Tensor] | None = None
    diagnostics: CodeDiagnostics | None = None
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"an EnvProfile needs a name, got {self.name!r}.")
        if not callable(self.make_env):
            raise ValueError(
                f"EnvProfile {self.name!r}: make_env must be a function that builds the env, "
                f"got {type(self.make_env).__name__}."
            )
        if self.diagnostics is not None and not isinstance(self.diagnostics, CodeDiagnostics):
            raise ValueError(
                f"EnvProfile {self.name!r}: diagnostics must be a CodeDiagnostics or None, got "
                f"{type(self.diagnostics).__name__}."
            )
        length = 1 if self.play_trajectory_length is None else self.play_trajectory_length
        if int(length) < 1 or int(self.default_num_objects) < 1:
            raise ValueError(
                f"EnvProfile {self.name!r}: play_trajectory_length and default_num_objects "
                f"must be >= 1, got {self.play_trajectory_length} and {self.default_num_objects}."
            )

    # ------------------------------------------------------------------ what it answers
    def resolve_num_objects(self, num_objects: int | None) -> int:
        """``num_objects``, or the default; an env that does not count objects takes only 1."""
        if num_objects is None:
            return self.default_num_objects if self.counts_objects else 1
        if not self.counts_objects and num_objects != 1:
            raise ValueError(
                f"num_objects={num_objects} applies to envs that count objects; "
                f"{self.name} does not (use num_objects=1 or None)."
            )
        return int(num_objects)

    def build(self, num_objects: int | None = None, **kwargs: Any) -> EnvBase:
        """The env with ``num_objects`` (if it counts them) and ``kwargs`` (``batch_size``,
        ``device``, ``seed``, ...).

        Raises:
            ValueError: ``make_env`` returned something that is not a TorchRL env.
        """
        num_objects = self.resolve_num_objects(num_objects)
        if self.counts_objects:
            kwargs["num_objects"] = num_objects
        env = self.make_env(**_accepted(self.make_env, kwargs))
        if not isinstance(env, EnvBase):
            raise ValueError(
                f"the make_env of profile {self.name!r} must return a TorchRL EnvBase, got "
                f"{type(env).__name__}."
            )
        return env

    def code_sizes(self, sizes: tuple[int, ...], num_objects: int) -> tuple[int, ...]:
        """The codes' one-hot sizes: one number laid out by :attr:`code_layout`, else as given."""
        sizes = tuple(int(s) for s in sizes)
        if len(sizes) == 1 and self.code_layout is not None:
            return tuple(self.code_layout(sizes[0], num_objects))
        return sizes

    def task_limit(self, num_objects: int | None = None, env: EnvBase | None = None) -> int:
        """Step limit of a task (:attr:`max_steps`, else ``env.max_steps``, else 200)."""
        n = self.resolve_num_objects(num_objects)
        limit = self.max_steps(n) if callable(self.max_steps) else self.max_steps
        if limit is None and env is not None:
            limit = getattr(env, "max_steps", None)
        return int(200 if limit is None else limit)

    def graph_groups(self, num_objects: int | None = None) -> Any:
        """The code graph's groups for ``num_objects``."""
        groups = self.groups
        return groups(self.resolve_num_objects(num_objects)) if callable(groups) else groups

    def code_overrides(self, num_objects: int | None = None) -> dict[str, Any]:
        """Representation-config fields that suit the env (empty: the config's defaults)."""
        n = self.resolve_num_objects(num_objects)
        return dict(self.codes(n)) if self.codes is not None else {}

    def world_model_overrides(self, num_objects: int | None = None) -> dict[str, Any]:
        """World-model-config fields that suit the env (empty: the config's defaults)."""
        n = self.resolve_num_objects(num_objects)
        return dict(self.world_model(n)) if self.world_model is not None else {}

    def latent_model_overrides(self, num_objects: int | None = None) -> dict[str, Any]:
        """Latent-world-model-config fields that suit the env (empty: the config's defaults)."""
        n = self.resolve_num_objects(num_objects)
        return dict(self.latent_model(n)) if self.latent_model is not None else {}

    def dorp_overrides(self, num_objects: int | None = None) -> dict[str, Any]:
        """DORP-config fields that suit the env with ``num_objects`` (empty: the defaults)."""
        if callable(self.dorp):
            return dict(self.dorp(self.resolve_num_objects(num_objects)))
        return dict(self.dorp)

    def tasks(self, env: EnvBase, num_tasks: int, seed: int) -> TensorDictBase:
        """``num_tasks`` tasks of ``env`` drawn with ``seed`` (:attr:`draw_tasks`), with
        ``lower_bound`` when the profile knows one."""
        draw = self.draw_tasks or reset_tasks
        tasks = draw(env, num_tasks, seed)
        if self.lower_bound is not None and "lower_bound" not in tasks.keys():
            bound = self.lower_bound(env, tasks["state"], tasks["goal_state"])
            tasks.set("lower_bound", torch.as_tensor(bound).reshape(num_tasks).to(torch.int64))
        return tasks


def _accepted(function: Callable[..., Any], kwargs: dict[str, Any]) -> dict[str, Any]:
    """``kwargs`` that ``function`` takes (all of them if it has ``**kwargs``)."""
    try:
        params = inspect.signature(function).parameters.values()
    except (TypeError, ValueError):
        return kwargs
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return kwargs
    names = {p.name for p in params}
    return {k: v for k, v in kwargs.items() if k in names}


_REGISTRY: dict[str, EnvProfile] = {}


def register_env_profile(profile: EnvProfile, *, replace: bool = False) -> EnvProfile:
    """Registers ``profile`` under its name (``--env <name>``); returns it.

    Raises:
        ValueError: the name is taken (pass ``replace=True`` to replace it).
    """
    if not isinstance(profile, EnvProfile):
        raise ValueError(f"register_env_profile takes an EnvProfile, got {type(profile).__name__}.")
    if profile.name in _REGISTRY and not replace and _REGISTRY[profile.name] is not profile:
        raise ValueError(f"an env profile is already registered as {profile.name!r}.")
    _REGISTRY[profile.name] = profile
    return profile


def registered_profiles() -> tuple[str, ...]:
    """Names of the registered profiles, in registration order."""
    return tuple(_REGISTRY)


def _import(path: str) -> Any:
    module_name, _, attribute = path.partition(":")
    if not module_name or not attribute:
        raise ValueError(
            f"env {path!r} is neither a registered profile ({', '.join(_REGISTRY)}) nor an "
            "import path 'package.module:attribute'. A profile made in code is known by its "
            "name once registered: call register_env_profile(profile) (or build a config "
            "with the profile) before loading a checkpoint trained on it."
        )
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ValueError(f"env {path!r}: cannot import {module_name!r} ({err}).") from None
    target: Any = module
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise ValueError(f"env {path!r}: {module_name!r} has no attribute {attribute!r}.")
        target = getattr(target, part)
    return target


def env_profile(env: str | EnvProfile) -> EnvProfile:
    """The profile of ``env``: a registered name, an import path or a profile itself.

    An import path ``"package.module:attribute"`` names an :class:`EnvProfile` or a
    function building a TorchRL env (given ``batch_size``, ``device`` and ``seed`` as far
    as it takes them); such a function gets a profile with the generic defaults, named
    by the path. An imported :class:`EnvProfile` is registered under its name.

    Raises:
        ValueError: naming what was given and what is accepted, or when another profile
            is registered under the imported profile's name.

    Examples:
        >>> from dorp_rl.envs import env_profile
        >>> env_profile("key-wall").play_trajectory_length
        1000
    """
    if isinstance(env, EnvProfile):
        return env
    if not isinstance(env, str):
        raise ValueError(
            f"env must be a profile name, an import path or an EnvProfile, got {type(env).__name__}."
        )
    if env in _REGISTRY:
        return _REGISTRY[env]
    target = _import(env)
    if isinstance(target, EnvProfile):
        # Known by its own name from now on too: a checkpoint trained on it records that
        # name (a config built with the profile itself), and loads in this process.
        return register_env_profile(target)
    if callable(target):
        return EnvProfile(name=env, make_env=target)
    raise ValueError(
        f"env {env!r} names a {type(target).__name__}; it must be an EnvProfile or a function "
        "that builds a TorchRL env."
    )


def profile_of(env: EnvBase) -> EnvProfile | None:
    """The registered profile whose ``env_type`` ``env`` is an instance of (the most
    specific one), or ``None``."""
    found = [
        p for p in _REGISTRY.values() if p.env_type is not None and isinstance(env, p.env_type)
    ]
    if not found:
        return None
    return max(found, key=lambda p: len(p.env_type.__mro__))
