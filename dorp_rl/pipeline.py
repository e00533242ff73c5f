"""The stages of the ``dorp`` command and the run folder they work in.

:class:`Run` holds a run folder ``<root>/<name>/`` (its lock, ``stages.json``, the log)
and runs each stage once per config (:meth:`Run.stage`); ``play_stage``, ``codes_stage``,
``graph_stage``, ``world_model_stage``, ``latent_model_stage`` and ``evaluate_stage`` are
the pipeline's stages, and the command dataclasses (:class:`Collect` ... :class:`Demo`)
their options, each a composition of the option groups it needs (:class:`RunOptions`,
:class:`CodeOptions`, :class:`WorldModelOptions`, :class:`LatentModelOptions`,
:class:`EvaluationOptions`, :class:`PaperOptions`). The
``dorp`` command (:mod:`dorp_rl.cli`) parses arguments into these and runs them;
``dorp reproduce --paper`` (:mod:`dorp_rl.reproduce`) runs them once per setting.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import torch
import tyro
from torchrl.envs import EnvBase

from dorp_rl.config import checked
from dorp_rl.data import collect_play_data
from dorp_rl.envs import DiscreteActions, env_identity
from dorp_rl.envs.paper import DEFAULT_SETTING, TABLE_1_SETTINGS
from dorp_rl.eval import (
    PAPER_SUCCESS,
    SETTINGS,
    EvalSpec,
    evaluate_parallel,
    failure_section,
    format_failures,
    make_task_set,
    paper_methods,
    result_row,
    setting_of,
    write_results,
    write_task_records,
)
from dorp_rl.eval.parallel import PLANNER_SHAPE
from dorp_rl.integrity import DirectoryLock, DirectoryLockedError, atomic_write_bytes
from dorp_rl.planners import CodeGraph, coupled_groups, encode_transitions, encoder_fingerprint
from dorp_rl.policies import DORPConfig
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    OfflineTrainer,
    RepresentationConfig,
    RepresentationTrainer,
    TrainingGaveUpError,
    WorldModelConfig,
    WorldModelTrainer,
    load_encoder,
)
from dorp_rl.validation import Int
from dorp_rl.viz import plot_results

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
#: the run folder's lock file (one command at a time in a run folder)
RUN_LOCK = "run.lock"
#: which command holds the run's lock (pid and command line), for the refusal's message
RUN_HOLDER = "running.json"
#: what a run name is, for the usage messages
NAME_RULE = "a run name is a folder below --root, such as 'demo' or 'paper/2obj'"


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


# --------------------------------------------------------------------------- runs and stages
class UsageError(ValueError):
    """Arguments that do not fit together (reported as a usage error, exit code 2)."""


def _flatten(values: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(values, dict):
        out: dict[str, Any] = {}
        for key, value in values.items():
            out.update(_flatten(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: values}


def _upgrade_stored(values: Any) -> Any:
    """A stored stage config in this version's terms: trainer configs of older versions
    (flat ``code_size`` / ``encoder_preset``, ``model_preset`` fields) read into the nested
    ones, so that an unchanged run is not re-run for the new layout alone."""
    if not isinstance(values, dict):
        return values
    for flat, cls in (("encoder_preset", RepresentationConfig), ("model_preset", WorldModelConfig)):
        if flat in values:
            try:
                return json.loads(json.dumps(_stage_config(cls.from_dict(values))))
            except (ValueError, TypeError):
                return values
    return {key: _upgrade_stored(value) for key, value in values.items()}


@contextmanager
def quiet_torchrl(active: bool) -> Iterator[None]:
    """Raises the ``torchrl`` logger to WARNING while ``active``, so that its INFO lines
    (e.g. "Initialized LazyMemmapStorage") do not land inside progress bars."""
    logger = logging.getLogger("torchrl")
    level = logger.level
    if active:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def run_folder(root: str, name: str) -> Path:
    """``<root>/<name>``, once checked to be a folder strictly below ``root``.

    Reads only (nothing is created). Symlinks are followed: a name that resolves to
    ``root`` itself or outside it is refused.

    Raises:
        UsageError: an empty, absolute or escaping ``name``, or a ``root`` (or a folder
            on its path) that is a file.
    """
    if not name.strip():
        raise UsageError(f"--name {name!r} is empty: {NAME_RULE}.")
    if Path(name).is_absolute():
        raise UsageError(f"--name {name!r} is an absolute path: {NAME_RULE}.")
    base = Path(root)
    existing = next((p for p in (base, *base.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise UsageError(
            f"--root {root}: {existing} is a file, not a folder. Give a folder for the runs "
            "(it is created if missing)."
        )
    try:
        inside, folder = base.resolve(), (base / name).resolve()
    except (OSError, RuntimeError, ValueError) as err:  # a symlink loop, a NUL byte
        raise UsageError(f"--name {name!r} cannot be resolved ({err}): {NAME_RULE}.") from None
    if folder == inside or inside not in folder.parents:
        where = "--root itself" if folder == inside else f"{folder}, outside --root {root}"
        raise UsageError(f"--name {name!r} is {where}: {NAME_RULE}.")
    path = base / name
    if path.exists() and not path.is_dir():
        raise UsageError(f"--name {name!r}: {path} is a file, not a run folder: {NAME_RULE}.")
    return path


def _read_stages(path: Path) -> dict[str, Any]:
    """The stage records of ``stages.json`` (none if the file is missing), checked.

    Raises:
        UsageError: a file that is not JSON, not a mapping of stage names to records, or
            a record without its ``config`` (or an evaluation's without its ``summary``).
    """
    if not path.exists():
        return {}
    problem, text = "", ""
    try:
        text = path.read_text()
        stages = json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as err:
        stages, problem = None, "it is empty" if not text.strip() else f"it is not JSON ({err})"
    if not problem and not isinstance(stages, dict):
        problem = f"it holds a {type(stages).__name__}, not a record per stage"
    for name, record in (stages if not problem else {}).items():
        config = record.get("config", ...) if isinstance(record, dict) else ...
        if config is ... or (config is not None and not isinstance(config, dict)):
            problem = f"stage {name!r} has no 'config' mapping"
        elif (
            config is not None
            and (name.startswith("evaluate:") or name == "pictures")
            and not isinstance(record.get("summary"), dict)
        ):
            problem = f"finished stage {name!r} has no 'summary' mapping"
        elif not isinstance(record.get("seconds", 0.0), (int, float)):
            problem = f"stage {name!r} has 'seconds' {record['seconds']!r}, not a number"
        if problem:
            break
    if problem:
        raise UsageError(
            f"{path} cannot be read as this run's stage records: {problem}. Remove it to "
            "run every stage again, or use another --name."
        )
    return stages


def _holder(directory: Path, settle: float = 1.0) -> str:
    """Who holds the run lock of ``directory``: pid, host, since and command if recorded.

    A command writes ``run.lock`` and then ``running.json`` just after it takes the lock,
    so a reader that comes in between waits up to ``settle`` seconds for both to name the
    same process before it reports what it has.
    """
    deadline = time.monotonic() + settle
    while True:
        try:
            lock = json.loads((directory / RUN_LOCK).read_text())
        except (OSError, ValueError):
            lock = None
        try:
            holder = json.loads((directory / RUN_HOLDER).read_text())
        except (OSError, ValueError):
            holder = None
        lock = lock if isinstance(lock, dict) else None
        holder = holder if isinstance(holder, dict) else {}
        settled = lock is not None and holder.get("pid") == lock.get("pid")
        if settled or time.monotonic() >= deadline:
            break
        time.sleep(0.02)
    if lock is None:
        return "another process"
    command = holder.get("command") if holder.get("pid") == lock.get("pid") else None
    what = f"{command}, " if command else ""
    return f"process {lock.get('pid')} on {lock.get('host')} ({what}since {lock.get('since')})"


def _lock_run(
    directory: Path, wait: bool, command_line: str, say: Callable[[str], None]
) -> DirectoryLock:
    """Takes the run lock of ``directory`` (creating the folder) for one command.

    Raises:
        UsageError: the run is busy and ``wait`` is false, or the folder cannot be written.
    """
    lock = DirectoryLock(directory, RUN_LOCK, purpose="a dorp command")
    try:
        try:
            lock.acquire()
        except DirectoryLockedError:
            if not wait:
                raise UsageError(
                    f"the run folder {directory} is in use by {_holder(directory)}: a second "
                    "command would remove files the first one is writing. Wait for it to "
                    "finish, add --wait to wait for it, or use another --name."
                ) from None
            say(f"the run folder {directory} is in use by {_holder(directory)}; waiting (--wait)")
            lock.acquire(wait=True)
        since = time.strftime("%Y-%m-%d %H:%M:%S")
        holder = {"pid": os.getpid(), "command": command_line, "since": since}
        atomic_write_bytes(directory / RUN_HOLDER, (json.dumps(holder) + "\n").encode())
    except OSError as err:
        lock.release()
        raise UsageError(
            f"cannot write in the run folder {directory}: {err.strerror or err}. Use a --root "
            "you can write in (or make this one writable)."
        ) from None
    return lock


class Run:
    """A run folder: resolved config, stage records, log and results.

    Holds the run's lock (``run.lock``) from its creation to :meth:`close` (or the end of
    a ``with`` block), so that one command at a time reads or changes the folder. Nothing
    is written into the folder before a stage runs (:meth:`begin_changes`): a command that
    stops with a usage error leaves it as it was, and the lines said until then go to
    ``log.txt`` only once the run changes.
    """

    #: seconds between updates of a running stage's time in ``stages.json``
    heartbeat: float = 30.0

    def __init__(
        self,
        command: Any,
        command_name: str,
        echo: Callable[[str], None] | None = None,
        command_line: str | None = None,
    ) -> None:
        self.command = command
        self.command_name = command_name
        #: where :meth:`say` prints (default: above any progress bar of this process)
        self.echo = echo
        #: the command line, as recorded for a second command refused on this run
        self.command_line = command_line or f"dorp {command_name}"
        self.dir = run_folder(command.root, command.name)
        self.progress = command.progress
        #: codes of the play data's transitions, by (codes variant, encoder fingerprint)
        self.encoded: dict[tuple[str, str], tuple[Any, Any]] = {}
        self.stages_path = self.dir / "stages.json"
        self._saving = threading.RLock()
        self._unsaid: list[str] | None = []  # log lines not yet in log.txt; None: written
        self._lock = _lock_run(
            self.dir, getattr(command, "wait", False), self.command_line, self._print
        )
        try:
            self.stages: dict[str, Any] = _read_stages(self.stages_path)
        except BaseException:
            self.close(changed=False)
            raise

    def _print(self, message: str) -> None:
        from tqdm.auto import tqdm

        (self.echo or tqdm.write)(message)

    def say(self, message: str) -> None:
        """Prints ``message`` (above any progress bar) and appends it to ``log.txt``."""
        self._print(message)
        line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {message}\n"
        if self._unsaid is not None:
            self._unsaid.append(line)
            return
        with (self.dir / "log.txt").open("a") as f:
            f.write(line)

    def begin_changes(self) -> None:
        """From here on this command changes the run folder: writes ``config.json`` (the
        resolved config) and the lines said so far into ``log.txt``. Once per run."""
        if self._unsaid is None:
            return
        resolved = {"command": self.command_name, **dataclasses.asdict(self.command)}
        (self.dir / "config.json").write_text(json.dumps(resolved, indent=2) + "\n")
        with (self.dir / "log.txt").open("a") as f:
            f.writelines(self._unsaid)
        self._unsaid = None

    def close(self, changed: bool = True) -> None:
        """Releases the run's lock; ``changed``: first write what :meth:`begin_changes`
        writes (a command that ran or failed), else leave the folder as it was."""
        if changed:
            self.begin_changes()
        if self._lock.held:
            (self.dir / RUN_HOLDER).unlink(missing_ok=True)
            self._lock.release()

    def __enter__(self) -> Run:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        usage = kind is not None and issubclass(kind, (UsageError, DirectoryLockedError))
        self.close(changed=not usage)

    def stage(
        self,
        name: str,
        config: dict[str, Any],
        outputs: Sequence[Path],
        build: Callable[[], tuple[Any, dict[str, Any]]],
        load: Callable[[], Any],
        resume: Callable[[], tuple[Any, dict[str, Any]]] | None = None,
    ) -> Any:
        """Runs ``build`` unless the stage is recorded with ``config`` and its ``outputs`` exist.

        ``build`` returns (value, summary); the summary is stored with the config. A
        stage that runs again first removes its old ``outputs`` (once no other process
        holds a library lock in them, e.g. a collection's), except that a stage with a
        ``resume`` which was stopped before it finished, with the same ``config``,
        calls ``resume`` on its outputs as they are: a training continues from its last
        checkpoint, an evaluation from its last finished chunk of tasks. While a stage
        runs, its record holds the seconds spent so far (updated every :attr:`heartbeat`
        seconds), so a stopped and resumed stage reports the time of both parts.

        Raises:
            UsageError: the finished stage's files do not load (replaced or damaged),
                naming them; nothing is changed.
            DirectoryLockedError: another process writes in one of ``outputs``.
        """
        config = json.loads(json.dumps(config))  # as stored: tuples become lists
        record = self.stages.get(name)
        if record is not None and record["config"] not in (None, config):
            record = {**record, "config": _upgrade_stored(record["config"])}
        if record is not None and record["config"] == config and all(p.exists() for p in outputs):
            try:
                value = load()
            except DirectoryLockedError:
                raise
            except (ValueError, OSError) as err:  # IntegrityError is a ValueError
                shown = ", ".join(str(p) for p in outputs) or str(self.stages_path)
                raise UsageError(
                    f"{shown} does not hold what stage {name} made: {err} Remove it to make "
                    "it again, or use another --name."
                ) from None
            self.say(f"{name}: done for this config, skipped{self._where(outputs)}")
            return value
        resuming = (
            resume is not None
            and record is not None
            and record["config"] is None
            and record.get("started") == config
            and all(p.exists() for p in outputs)
        )
        if record is None:
            reason = "not run yet"
        elif resuming:
            reason = "it did not finish last time; resuming where it stopped"
        elif record["config"] is None:
            reason = "it did not finish last time"
        elif record["config"] != config:
            old, new = _flatten(record["config"]), _flatten(config)
            changed = [
                k
                for k in sorted(set(old) | set(new))
                if old.get(k) != new.get(k) or (k in old) != (k in new)
            ]

            def show(values: dict[str, Any], key: str) -> str:
                return repr(values[key]) if key in values else "(no such field)"

            shown = ", ".join(f"{k} {show(old, k)} -> {show(new, k)}" for k in changed[:6])
            more = f" and {len(changed) - 6} more" if len(changed) > 6 else ""
            reason = f"changed: {shown}{more}"
        else:
            reason = "its files are missing"
        claimed = [] if resuming else _claim_outputs(outputs)
        self.begin_changes()
        self.say(f"{name}: running ({reason})")
        before = float(record.get("seconds", 0.0)) if resuming and record is not None else 0.0
        # Unfinished until build returns; the record keeps its place (and its row's).
        self._record(name, {"config": None, "started": config, "seconds": before})
        try:
            for path in [] if resuming else outputs:
                _remove(path)
        finally:
            for lock in claimed:
                lock.release()
        start = time.perf_counter()
        stop = threading.Event()

        def beat() -> None:
            while not stop.wait(self.heartbeat):
                so_far = before + time.perf_counter() - start
                self._record(name, {"config": None, "started": config, "seconds": so_far})

        beating = threading.Thread(target=beat, name=f"stage {name} heartbeat", daemon=True)
        beating.start()
        try:
            with quiet_torchrl(self.progress):
                value, summary = (resume if resuming else build)()  # type: ignore[misc]
        finally:
            stop.set()
            beating.join()
        seconds = before + time.perf_counter() - start
        self._record(name, {"config": config, "summary": summary, "seconds": seconds})
        self.say(f"{name}: done in {seconds:.0f} s{self._where(outputs)}")
        return value

    def _where(self, outputs: Sequence[Path]) -> str:
        return f" ({', '.join(str(p) for p in outputs)})" if outputs else ""

    def _record(self, name: str, record: dict[str, Any]) -> None:
        """Sets and saves the record of stage ``name`` (a running stage's heartbeat too)."""
        with self._saving:
            self.stages[name] = record
            self._save()

    def _save(self) -> None:
        with self._saving:
            tmp = self.stages_path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.stages, indent=2) + "\n")
            tmp.replace(self.stages_path)

    def result_rows(self) -> list[dict[str, Any]]:
        """The rows of every finished evaluation stage, in the order they were run."""
        return [
            r["summary"]
            for k, r in self.stages.items()
            if k.startswith("evaluate:") and r["config"] is not None
        ]


def _claim_outputs(outputs: Sequence[Path]) -> list[DirectoryLock]:
    """Takes every library lock (``*.lock``: a collection's, a training's) found in the
    folders of ``outputs``, so that they are not removed under another process.

    Raises:
        DirectoryLockedError: one is held (the locks taken so far are released).
    """
    claimed: list[DirectoryLock] = []
    try:
        for path in outputs:
            for lock_file in sorted(path.glob("*.lock")) if path.is_dir() else ():
                claimed.append(DirectoryLock(path, lock_file.name).acquire())
    except BaseException:
        for lock in claimed:
            lock.release()
        raise
    return claimed


def _remove(path: Path) -> None:
    """Removes a stage output before the stage runs again (the run folder is the CLI's)."""
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


# --------------------------------------------------------------------------- stages
def _stage_config(cfg: Any) -> dict[str, Any]:
    """A trainer config without the fields that never change its result (paths, progress)."""
    return {k: v for k, v in cfg.to_dict().items() if k not in OfflineTrainer.bookkeeping_fields}


def _play_config(codes: RepresentationConfig) -> dict[str, Any]:
    values = codes.to_dict()
    return {k: values[k] for k in PLAY_FIELDS}


def play_stage(run: Run, codes: RepresentationConfig):
    """The play data the codes train on (collected into ``play/``, or loaded)."""
    directory = run.dir / "play"

    def collect(progress: bool):
        env = codes.make_env(batch_size=(codes.num_envs,))
        return collect_play_data(
            env,
            codes.num_frames,
            directory=directory,
            seed=codes.seed,
            trajectory_length=codes.play_trajectory_length,
            progress=progress,
        )

    def build():
        length, why = codes.play_length_choice()
        summary: dict[str, Any] = {}
        if why is not None:  # chosen from the env's resets
            say_chosen(run, "play", {"trajectory_length": {"value": length, "why": why}})
            summary["chosen"] = {"trajectory_length": length}
        buffer = collect(run.progress)
        return buffer, {"frames": len(buffer), **summary}

    return run.stage(
        "play", _play_config(codes), [directory], build, lambda: collect(progress=False)
    )


def say_chosen(run: Run, stage: str, chosen: dict[str, dict[str, Any]]) -> None:
    """Writes each setting a trainer chose from the env (``{field: {"value", "why"}}``) to
    the run's log, as ``<stage>: chose <field> = <value> (<why>)``."""
    for name, choice in chosen.items():
        run.say(f"{stage}: chose {name} = {choice['value']} ({choice['why']})")


def _tagged(name: str, variant: str, sep: str = ":") -> str:
    return f"{name}{sep}{variant}" if variant else name


def codes_stage(run: Run, codes: RepresentationConfig, variant: str = ""):
    """The trained encoder (trained into ``codes/``, or loaded); play data first.

    A ``variant`` (e.g. ``"arbitrary"``) is a stage of its own, ``codes:<variant>`` in
    ``codes-<variant>/``, on the same play data.
    """
    buffer = play_stage(run, codes)
    codes_dir = run.dir / _tagged("codes", variant, "-")
    cfg = replace(
        codes,
        out_dir=str(codes_dir),
        data_dir=str(run.dir / "play"),
        progress=run.progress,
    )
    checkpoint = codes_dir / "checkpoints" / "last.pt"

    def build(resume: bool = False):
        trainer = RepresentationTrainer(cfg, buffer=buffer)
        say_chosen(run, _tagged("codes", variant), trainer.chosen)
        result = trainer.train(resume=resume)
        if result["gave_up"] is not None:
            raise TrainingGaveUpError(f"{_tagged('codes', variant)}: {result['gave_up']}")
        diagnostics = trainer.evaluate()
        summary = {
            k: diagnostics[k]
            for k in ("selectivity", "purity", "codes_used")
            if k in diagnostics and isinstance(diagnostics[k], (int, float, list))
        }
        if summary:
            run.say(f"{_tagged('codes', variant)}: {json.dumps(summary)}")
        if trainer.chosen:
            summary["chosen"] = {k: c["value"] for k, c in trainer.chosen.items()}
        return trainer.encoder.eval(), summary

    def load():
        return load_encoder(checkpoint, codes.make_env())

    name = _tagged("codes", variant)
    resume = functools.partial(build, resume=True)
    encoder = run.stage(name, _stage_config(cfg), [codes_dir], build, load, resume)
    return encoder, buffer


def graph_stage(
    run: Run,
    codes: RepresentationConfig,
    setting: str,
    variant: str = "",
    codes_variant: str = "",
    groups: Any = None,
):
    """The code graph over the play data (built into ``graph.pt``, or loaded); codes first.

    A ``variant`` is stage ``graph:<variant>`` in ``graph-<variant>.pt``, over the codes
    of ``codes_variant`` with ``groups`` (default: the setting's).
    """
    encoder, buffer = codes_stage(run, codes, codes_variant)
    path = run.dir / f"{_tagged('graph', variant, '-')}.pt"
    groups = setting_of(setting).groups if groups is None else groups
    env = codes.make_env()
    env_config, num_actions = env_identity(env), DiscreteActions.of(env).num_actions

    def build():
        # Graphs over one codes variant (per group, full) share one encoding of the play data.
        key = (codes_variant, encoder_fingerprint(encoder))
        if key not in run.encoded:
            run.encoded[key] = encode_transitions(buffer, encoder, progress=run.progress)
        chosen = groups
        if isinstance(groups, str) and groups == "auto":
            choice = coupled_groups(*run.encoded[key])
            chosen = choice.groups
            say_chosen(run, "graph", {"groups": {"value": list(chosen), "why": choice.why}})
        graph = setting_of(setting).make_graph(
            buffer, encoder, chosen, transitions=run.encoded[key], num_actions=num_actions
        )
        graph.save(path)
        nodes = [graph.num_nodes(g) for g in range(graph.num_groups)]
        return graph, {"nodes": nodes, "groups": [list(g) for g in graph.groups]}

    def load():
        return CodeGraph.load(path, encoder=encoder, env_config=env_config)

    # "action_counts": graphs keep their play data's actions (older graphs are rebuilt).
    config = {
        "groups": groups,
        "codes": _stage_config(codes),
        "action_counts": True,
        "completed": setting_of(setting).completes_graph(groups),
    }
    return encoder, run.stage(_tagged("graph", variant), config, [path], build, load)


def dorp_stages(run: Run, cmd: Evaluate | Reproduce, method: str) -> tuple[Any, Any, str]:
    """Encoder, graph and graph stage name of DORP or one of its ablations
    (:data:`DORP_VARIANTS`), each trained or built once per run."""
    similarity, groups = DORP_VARIANTS[method]
    variant = method.removeprefix("dorp").removeprefix("-")
    codes, codes_variant = cmd.codes, ""
    if similarity is not None and similarity != codes.similarity:
        codes = replace(codes, similarity=similarity, alpha=1.0, dddp_sign="paper")
        codes_variant = variant
    encoder, graph = graph_stage(run, codes, cmd.setting, variant, codes_variant, groups)
    return encoder, graph, _tagged("graph", variant)


def _model_stage(run: Run, folder: str, trainer: Any, cfg: Any, metric: str, config: Any) -> Path:
    """A world model's checkpoint: trained by ``trainer(cfg)`` into ``<folder>/`` (its play
    data in ``<folder>_play/``) as the stage ``folder``, resumed, or found."""
    checkpoint = run.dir / folder / "checkpoints" / "last.pt"

    def build(resume: bool = False):
        model_trainer = trainer(cfg)
        chosen = getattr(model_trainer, "chosen", {})
        say_chosen(run, folder, chosen)
        result = model_trainer.train(resume=resume)
        summary = {metric: result.get("evaluation", {}).get(metric)}
        if chosen:
            summary["chosen"] = {k: c["value"] for k, c in chosen.items()}
        return checkpoint, summary

    outputs = [run.dir / folder, run.dir / f"{folder}_play"]
    resume = functools.partial(build, resume=True)
    run.stage(folder, config, outputs, build, lambda: checkpoint, resume)
    return checkpoint


def _in_run(run: Run, cfg: Any, folder: str, **more: Any) -> Any:
    """``cfg`` writing into the run folder: ``<folder>/``, its play data, the run's bars."""
    return replace(
        cfg,
        out_dir=str(run.dir / folder),
        data_dir=str(run.dir / f"{folder}_play"),
        progress=run.progress,
        **more,
    )


def world_model_stage(run: Run, world_model: WorldModelConfig) -> Path:
    """The world-model checkpoint (trained into ``world_model/``, or found)."""
    cfg = _in_run(run, world_model, "world_model")
    return _model_stage(
        run, "world_model", WorldModelTrainer, cfg, "exact_accuracy_last", _stage_config(cfg)
    )


def latent_model_stage(
    run: Run, latent_model: LatentWorldModelConfig, codes: RepresentationConfig
) -> Path:
    """The latent world-model checkpoint (trained into ``latent_model/`` on the run's
    codes, trained first if needed, or found)."""
    codes_stage(run, codes)
    encoder = str(run.dir / "codes" / "checkpoints" / "last.pt")
    cfg = _in_run(run, latent_model, "latent_model", encoder_checkpoint=encoder)
    config = {"latent_model": _stage_config(cfg), "codes": _stage_config(codes)}
    return _model_stage(
        run, "latent_model", LatentWorldModelTrainer, cfg, "code_accuracy_last", config
    )


def _policy(cmd: Evaluate | Reproduce, method: str, env: EnvBase, low_level: Any, dorp: Any):
    """The policy of ``method`` for ``env``, built by the same recipe as the workers'."""
    if method == "random":
        torch.manual_seed(cmd.seed)
    dorp_method = method in DORP_VARIANTS
    spec = EvalSpec(
        cmd.setting,
        "dorp" if dorp_method else method,
        encoder=dorp[0] if dorp_method else None,
        graph=dorp[1] if dorp_method else None,
        low_level="gt" if low_level is None else str(low_level),
        candidates=cmd.candidates,
        planning_horizon=cmd.planning_horizon,
        dorp=cmd.dorp.overrides(),
        seed=cmd.seed,
    )
    return spec.make_policy(env)


def task_set(cmd: Evaluate | Reproduce, env: EnvBase) -> tuple[Any, int]:
    """The seeded task set of ``cmd`` on ``env`` (drawn by the setting's env profile) and
    the step limit (``--max-steps``, else the profile's): what the evaluation runs, and
    the rollout GIFs run again."""
    setting = setting_of(cmd.setting)
    tasks = make_task_set(env, cmd.tasks, seed=cmd.task_seed, profile=setting.profile)
    return tasks, cmd.max_steps or setting.profile.task_limit(setting.num_objects, env)


def evaluate_stage(run: Run, cmd: Evaluate | Reproduce) -> list[dict[str, Any]]:
    """Every method of ``cmd`` on the seeded task set; returns the run's result rows."""
    setting = setting_of(cmd.setting)
    low_level: Path | None = None  # None: the true dynamics
    low_config: Any = "gt"
    level_name = cmd.low_level
    if cmd.low_level == "world-model":
        low_level = world_model_stage(run, cmd.world_model)
        low_config = _stage_config(cmd.world_model)
    elif cmd.low_level == "latent-model":
        low_level = latent_model_stage(run, cmd.latent_model, cmd.codes)
        low_config = {"latent_model": _stage_config(cmd.latent_model)}
    elif cmd.low_level != "gt":
        low_level, level_name = Path(cmd.low_level), "checkpoint"
        low_config = {"path": str(low_level.resolve()), "mtime": low_level.stat().st_mtime}
    batch = min(cmd.tasks, cmd.tasks_per_rollout)
    for method in cmd.methods:
        dorp = dorp_stages(run, cmd, method) if method in DORP_VARIANTS else None
        config: dict[str, Any] = {
            k: getattr(cmd, k) for k in ("setting", "tasks", "task_seed", "seed", "max_steps")
        }
        config["tasks_per_rollout"] = batch
        if method != "random":
            config.update(
                low_level=low_config,
                candidates=cmd.candidates,
                planning_horizon=cmd.planning_horizon,
            )
        if dorp is not None:
            config.update(
                dorp=cmd.dorp.overrides(),
                graph=run.stages[dorp[2]]["config"],
                dorp_where_suited=dict(DORPConfig.WHERE_SUITED),
            )

        key = f"evaluate:{method}" + ("" if method == "random" else f":{level_name}")
        # Finished chunks of tasks, so a stopped evaluation resumes at the next chunk.
        chunk_file = run.dir / "evaluations" / (key.replace(":", "-") + ".json")

        def build(
            resume: bool = False,
            method: str = method,
            dorp: Any = dorp,
            chunk_file: Path = chunk_file,
        ) -> tuple[None, dict[str, Any]]:
            if not resume:
                chunk_file.unlink(missing_ok=True)  # from another config, or none
            # Picklable factories: --workers/--backend rebuild env and policy per worker;
            # the policy is reseeded with seed + k per chunk k, so any --workers agrees.
            make_env = functools.partial(setting.make_env, batch_size=(batch,), seed=cmd.seed)
            tasks, limit = task_set(cmd, make_env())
            result = evaluate_parallel(
                make_env,
                functools.partial(_policy, cmd, method, low_level=low_level, dorp=dorp),
                tasks,
                seed=cmd.seed,
                max_steps=limit,
                tasks_per_rollout=batch,
                workers=cmd.workers,
                backend=cmd.backend,
                address=cmd.address,
                progress=run.progress,
                resume_file=chunk_file,
            )
            chunk_file.unlink()  # its per-task results go into the stage's record
            level = "none" if method == "random" else level_name
            row = result_row(result, tasks, setting=cmd.setting, method=method, low_level=level)
            row["per_task"] = {  # for the steps plot and tasks.csv; not results.csv columns
                "success": result["success"],
                "steps": result["steps"],
                "lower_bound": (  # nan: the env's profile knows no bound
                    tasks["lower_bound"].tolist()
                    if "lower_bound" in tasks.keys()
                    else [math.nan] * cmd.tasks
                ),
                "records": result["records"],
            }
            run.say(
                f"{method}: success {row['success_rate']:.2f}, {row['mean_steps']:.1f} steps "
                f"(lower bound {row['mean_lower_bound']:.1f}), "
                f"{row['seconds_per_task']:.1f} s per task"
            )
            run.say(format_failures(result["records"], method))
            return None, row

        resume = functools.partial(build, resume=True)
        run.stage(key, config, [], build, lambda: None, resume)
    rows = run.result_rows()
    figures = plot_results(rows, run.dir, PAPER_SUCCESS)
    write_results(rows, run.dir, figures, sections=[failure_section(rows)])
    write_task_records(rows, run.dir / "tasks.csv")
    return rows
