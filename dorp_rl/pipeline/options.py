"""The ``dorp`` command's options: the option groups, each checking its own options
(:class:`RunOptions`, :class:`CodeOptions`, :class:`WorldModelOptions`,
:class:`LatentModelOptions`, :class:`EvaluationOptions`, :class:`PaperOptions`), and the
subcommands (:class:`Collect` ... :class:`Demo`), each a flat composition of the groups it
needs, with their defaults under a setting (:func:`default_command`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

import tyro

from dorp_rl.config import Int, checked
from dorp_rl.envs.paper import DEFAULT_SETTING, TABLE_1_SETTINGS
from dorp_rl.eval import (
    SETTINGS,
    paper_methods,
    setting_of,
)
from dorp_rl.eval.parallel import PLANNER_SHAPE
from dorp_rl.pipeline.run import UsageError, run_folder
from dorp_rl.policies import DORPConfig
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    RepresentationConfig,
    WorldModelConfig,
)

__all__ = [
    "COMMANDS",
    "DEMO_CODE_STEPS",
    "DORP_VARIANTS",
    "LOW_LEVEL_NAMES",
    "PLAY_FIELDS",
    "BuildGraph",
    "CodeOptions",
    "Collect",
    "DORPOptions",
    "Demo",
    "Evaluate",
    "EvaluationOptions",
    "LatentModelOptions",
    "PaperOptions",
    "Reproduce",
    "RunOptions",
    "TrainEncoder",
    "TrainWorldModel",
    "WorldModelOptions",
    "default_command",
]


#: the paper's settings by name (dorp_rl.eval.SETTINGS), as the command's choices
SettingName = Literal.__getitem__(tuple(SETTINGS))  # type: ignore[misc]


Method = Literal[
    "dorp", "dorp-arbitrary", "dorp-identity", "dorp-full", "vf-rs", "vf-cem", "random"
]


#: DORP and its ablations (the paper's Table 1): method -> (similarity of its codes, graph
#: groups); None keeps the codes' own similarity / the setting's groups. The ablations
#: train codes of their own (arbitrary: a learned matrix, identity: the identity) or plan
#: over whole codes (full graph) with DORP's codes.
DORP_VARIANTS: dict[str, tuple[str | None, Any]] = {
    "dorp": (None, None),
    "dorp-arbitrary": ("full", None),
    "dorp-identity": ("identity", None),
    "dorp-full": (None, "full"),
}


#: fields of a representation config that decide its play data
PLAY_FIELDS = (
    "env",
    "num_objects",
    "num_frames",
    "num_envs",
    "trajectory_length",
    "seed",
    "device",
)


#: other names of --low-level values
LOW_LEVEL_NAMES = {"ground-truth": "gt", "video": "world-model"}


#: training steps of the demo's codes (the preset's 1500 do not fit its 5-minute budget)
DEMO_CODE_STEPS = 1000


# --------------------------------------------------------------------------- configs
# The option groups, each checking its own options (``check``), then the subcommands
# composed of them; the rules joining two groups are in dorp_rl.cli (``_check``).
@dataclass
class RunOptions:
    """Where a run lives and how it runs."""

    name: str = "demo"
    """run name: every file of the run goes to <root>/<name>/, a folder strictly below
    --root (such as 'demo' or 'paper/2obj'; not absolute, not '.', not out of --root)"""
    root: str = "runs"
    """folder holding the runs (created if missing; it must be writable)"""
    threads: int = 1
    """torch threads (torch.set_num_threads). Keep 1 on a shared 2-core machine: there,
    oversubscribed threads made a training step about 100x slower."""
    progress: bool = True
    """show progress bars on long stages"""
    setting: SettingName = DEFAULT_SETTING
    """environment, code preset and graph groups (dorp_rl.eval.SETTINGS); the codes and
    world-model fields below default to this setting's presets"""
    env: str | None = None
    """your own environment instead of --setting: a registered env profile or an import
    path 'package.module:attribute' (an EnvProfile, or a function that builds a TorchRL
    env with discrete actions and 'pixels'); its profile's presets fill in the fields below"""
    wait: bool = False
    """when another dorp command is running in the run folder: wait until it has finished,
    then go on (default: stop at once with exit code 2)"""

    def check(self, command: str) -> None:
        """``--env`` is an env profile, ``--name`` a folder below a usable ``--root``
        (:func:`run_folder`, which writes nothing), ``--threads >= 1``."""
        if self.env is not None:
            try:
                setting_of(self.env)
            except ValueError as err:
                raise UsageError(f"--env {self.env}: {err}") from None
        setting_of(self.setting)
        run_folder(self.root, self.name)
        if self.threads < 1:
            raise UsageError(f"--threads must be >= 1, got {self.threads}.")


def _default_setting() -> tuple[str, int]:
    setting = SETTINGS[DEFAULT_SETTING]
    return setting.env, setting.num_objects


def _codes_default() -> RepresentationConfig:
    return RepresentationConfig.for_env(*_default_setting())


def _world_model_default() -> WorldModelConfig:
    return WorldModelConfig.for_env(*_default_setting())


def _latent_model_default() -> LatentWorldModelConfig:
    return LatentWorldModelConfig.for_env(*_default_setting())


@dataclass
class CodeOptions:
    """The representation config: the play data and the codes trained on them."""

    codes: RepresentationConfig = field(default_factory=_codes_default)
    """representation config; its env, num_objects, num_frames, num_envs,
    trajectory_length, seed and device decide the play data"""

    def check(self, command: str) -> None:
        """Nothing of its own: the config checks its fields when it is built (a parse
        error); its env and bookkeeping fields are checked against the run's."""


@dataclass
class WorldModelOptions:
    """The world-model config (the video prediction model and its play data)."""

    world_model: WorldModelConfig = field(default_factory=_world_model_default)
    """world-model config (default: the setting's preset)"""

    def check(self, command: str) -> None:
        """Nothing of its own: the config checks its fields when it is built (a parse
        error); its env and bookkeeping fields are checked against the run's."""


@dataclass
class LatentModelOptions:
    """The latent world-model config (trained on the run's codes, with its own play data)."""

    latent_model: LatentWorldModelConfig = field(default_factory=_latent_model_default)
    """latent world-model config, used when --low-level latent-model (default: the
    setting's preset; its encoder is the run's codes)"""

    def check(self, command: str) -> None:
        """Nothing of its own: the config checks its fields when it is built (a parse
        error); its env and bookkeeping fields are checked against the run's."""
        if self.latent_model.encoder_checkpoint is not None:
            raise UsageError(
                "--latent-model.encoder-checkpoint is set by the run: the latent world "
                "model learns the run's codes (codes/checkpoints/last.pt)."
            )


@dataclass
class DORPOptions(DORPConfig):
    """DORP's settings (``--dorp.<field>``), by default those of the env's profile; the
    planners' shape is ``--candidates`` / ``--planning-horizon``, as for every method."""

    planning_horizon: tyro.conf.Suppress[int] = checked(14, Int(low=1))
    num_candidates: tyro.conf.Suppress[int] = checked(1000, Int(low=1))

    def overrides(self) -> dict[str, Any]:
        """Every field but the planners' shape, as plain values (``EvalSpec.dorp``)."""
        values = self.to_dict()
        return {k: v for k, v in values.items() if k not in PLANNER_SHAPE}


def _dorp_default() -> DORPOptions:
    env, num_objects = _default_setting()
    return DORPOptions(**DORPConfig.for_env(env, num_objects=num_objects).to_dict())


@dataclass
class EvaluationOptions:
    """Which methods run on which seeded tasks, how they plan and where they run."""

    methods: tuple[Method, ...] = ("dorp",)
    """methods: dorp (code graph + MPC), its ablations dorp-arbitrary / dorp-identity
    (codes with another similarity) and dorp-full (one graph over whole codes), vf-rs /
    vf-cem (visual foresight), random"""
    low_level: str = "gt"
    """planning model: 'gt' (the true dynamics), 'world-model' (this run's video
    prediction model, trained first if needed), 'latent-model' (this run's latent world
    model of its codes, trained first if needed) or the path of a checkpoint of either;
    'ground-truth' and 'video' are other names of 'gt' and 'world-model'"""
    tasks: int = 10
    """tasks of the seeded task set (dorp_rl.eval.make_task_set)"""
    task_seed: int = 0
    """seed of the task set: the same tasks for every method"""
    seed: int = 0
    """seed of the planners (and of the random policy)"""
    tasks_per_rollout: int = 10
    """tasks run side by side in one batched rollout"""
    candidates: int = 1000
    """action sequences per plan"""
    planning_horizon: int = 14
    """steps per candidate sequence"""
    dorp: DORPOptions = field(default_factory=_dorp_default)
    """DORP's settings (default: the env profile's; see dorp_rl.policies.DORPConfig)"""
    max_steps: int | None = None
    """step limit per task (default: the env's, 400 for 2 objects, 1400 for 5)"""
    workers: int = 1
    """processes (or Ray actors) the tasks are spread over, chunk by chunk, one torch thread
    each; the results equal a one-process run (dorp_rl.eval.evaluate_parallel). With
    reproduce --paper and the local backend, up to this many settings run side by side
    instead (longest first), each with the workers left over"""
    backend: Literal["local", "ray"] = "local"
    """'local': worker processes on this machine; 'ray': Ray actors on a cluster
    (pip install dorp-rl[ray])"""
    address: str | None = None
    """--backend ray: the cluster to join ('auto', 'ray://host:port'); default: a running
    Ray or a new local one"""
    gifs: int = 2
    """DORP rollouts (the first tasks of the set) drawn as GIFs into pictures/, beside the
    code maps and factorisation histogram of the codes (0: no GIFs)"""

    def check(self, command: str) -> None:
        """Counts ``>= 1`` (``--gifs >= 0``), seeds ``>= 0``, at least one method,
        ``--address`` only with ``--backend ray``. (A ``--low-level`` file is checked
        against the run's setting.)"""
        for name in (
            "tasks",
            "tasks_per_rollout",
            "candidates",
            "planning_horizon",
        ):
            if getattr(self, name) < 1:
                raise UsageError(
                    f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}."
                )
        if self.max_steps is not None and self.max_steps < 1:
            raise UsageError(
                f"--max-steps must be >= 1 (or None: the env's limit), got {self.max_steps}."
            )
        for name in ("seed", "task_seed"):
            if getattr(self, name) < 0:
                raise UsageError(
                    f"--{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}."
                )
        if not self.methods:
            raise UsageError("--methods needs at least one method.")
        if self.workers < 1:
            raise UsageError(f"--workers must be >= 1, got {self.workers}.")
        if self.address is not None and self.backend != "ray":
            raise UsageError("--address is for --backend ray (the Ray cluster to join).")
        if self.gifs < 0:
            raise UsageError(f"--gifs must be >= 0, got {self.gifs}.")


@dataclass
class PaperOptions:
    """``reproduce --paper``: the paper's Table 1 over several settings (and seeds)."""

    paper: bool = False
    """the paper's Table 1 instead of one setting: every method of the table in each of
    --settings, one sub-run per setting (<name>/<setting>/), one table and timings.csv
    in the run folder; --codes.* / --world-model.* / --dorp.* changes apply to every setting"""
    settings: tuple[SettingName, ...] = TABLE_1_SETTINGS
    """with --paper: the settings to run"""
    paper_methods: tuple[Method, ...] = ()
    """with --paper: run only these of each setting's Table 1 methods (empty: all of them);
    a setting where Table 1 has none of them is left out, and the run says so"""
    seeds: tuple[int, ...] = ()
    """with --paper: run every setting once per seed (its codes', world model's and
    planners' seed; the tasks stay those of --task-seed), in sub-runs <setting>-seed<k>/,
    and pool the results over seeds (success rate ± std over seeds); empty: one run with
    --seed and the presets' seeds"""

    def check(self, command: str) -> None:
        """``--paper-methods`` and ``--seeds`` only with ``--paper``, an option of
        reproduce alone; with it, at least one setting, ``--paper-methods`` of Table 1 in
        some of them, distinct seeds ``>= 0``."""
        if self.paper_methods and not self.paper:
            raise UsageError(
                "--paper-methods is an option of reproduce --paper (which of Table 1's "
                "methods to run); for one setting, use --methods."
            )
        if self.seeds and not self.paper:
            raise UsageError(
                "--seeds is an option of reproduce --paper (one sub-run per setting and "
                "seed); for one run, set --seed and --codes.seed."
            )
        if not self.paper:
            return
        if command != "reproduce":
            raise UsageError(f"--paper is an option of reproduce, not of {command}.")
        if not self.settings:
            raise UsageError("--settings needs at least one setting.")
        if self.paper_methods:
            in_table = {m for setting in self.settings for m in paper_methods(setting)}
            missing = [m for m in self.paper_methods if m not in in_table]
            if missing:
                raise UsageError(
                    f"--paper-methods {' '.join(missing)}: not in Table 1 for the settings "
                    f"{' '.join(self.settings)}, whose methods are {', '.join(sorted(in_table))}."
                )
        if any(seed < 0 for seed in self.seeds) or len(set(self.seeds)) != len(self.seeds):
            raise UsageError(f"--seeds must be distinct and >= 0, got {list(self.seeds)}.")


@dataclass
class Collect(CodeOptions, RunOptions):
    """Collect the setting's random play data (the data the codes train on) into play/."""


@dataclass
class TrainEncoder(CodeOptions, RunOptions):
    """Train the discrete codes (play data first) into codes/."""


@dataclass
class BuildGraph(CodeOptions, RunOptions):
    """Build the code graph over the play data (codes first) into graph.pt."""


@dataclass
class TrainWorldModel(WorldModelOptions, RunOptions):
    """Train the video prediction model (with its own play data) into world_model/."""


@dataclass
class Evaluate(EvaluationOptions, LatentModelOptions, WorldModelOptions, CodeOptions, RunOptions):
    """Evaluate methods on a seeded task set; results go to results.csv and results.md."""

    world_model: WorldModelConfig = field(default_factory=_world_model_default)
    """world-model config, used when --low-level world-model"""


@dataclass
class Reproduce(
    PaperOptions, EvaluationOptions, LatentModelOptions, WorldModelOptions, CodeOptions, RunOptions
):
    """The whole pipeline for one setting: play data, codes, graph, then DORP and VF-CEM."""

    world_model: WorldModelConfig = field(default_factory=_world_model_default)
    """world-model config, used when --low-level world-model"""
    methods: tuple[Method, ...] = ("dorp", "vf-cem")
    """methods: dorp (code graph + MPC), its ablations dorp-arbitrary / dorp-identity
    (codes with another similarity) and dorp-full (one graph over whole codes), vf-rs /
    vf-cem (visual foresight), random"""
    tasks: int = 50
    """tasks of the seeded task set (dorp_rl.eval.make_task_set); the paper used 50"""


@dataclass
class Demo(Reproduce):
    """A small reproduce: 2 objects, shorter code training, DORP and VF-CEM on 10 tasks."""

    tasks: int = 10
    """tasks of the seeded task set (dorp_rl.eval.make_task_set)"""


#: subcommand name -> its dataclass
COMMANDS: dict[str, type] = {
    "collect": Collect,
    "train-encoder": TrainEncoder,
    "train-world-model": TrainWorldModel,
    "build-graph": BuildGraph,
    "evaluate": Evaluate,
    "reproduce": Reproduce,
    "demo": Demo,
}


def default_command(name: str, setting: str = DEFAULT_SETTING) -> Any:
    """The defaults of subcommand ``name`` under ``setting`` (its presets filled in): a
    paper setting, or an env profile's name or import path (given as ``--env``)."""
    cls = COMMANDS[name]
    # A setting that is no paper setting is an env profile: --env.
    values: dict[str, Any] = (
        {"setting": setting}
        if setting in SETTINGS
        else {"setting": DEFAULT_SETTING, "env": setting}
    )
    fields = {f.name for f in dataclasses.fields(cls)}
    if "codes" in fields:
        steps = {"num_steps": DEMO_CODE_STEPS} if cls is Demo else {}
        chosen = setting_of(setting)
        values["codes"] = RepresentationConfig.for_env(chosen.env, chosen.num_objects, **steps)
    if "world_model" in fields:
        chosen = setting_of(setting)
        values["world_model"] = WorldModelConfig.for_env(chosen.env, chosen.num_objects)
    if "latent_model" in fields:
        chosen = setting_of(setting)
        values["latent_model"] = LatentWorldModelConfig.for_env(chosen.env, chosen.num_objects)
    if "dorp" in fields:
        chosen = setting_of(setting)
        suited = DORPConfig.for_env(chosen.profile, num_objects=chosen.num_objects)
        values["dorp"] = DORPOptions(**suited.to_dict())
    return cls(**values)
