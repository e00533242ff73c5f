"""The ``dorp`` command: play data, codes, code graph, world model and evaluation as stages.

Every command works in a run folder ``<root>/<name>/`` (default ``runs/demo/``):

- ``config.json``: the resolved config of the last command (every field, after presets);
- ``stages.json``: per finished stage, the config it was made with (and a summary);
- ``play/``, ``codes/``, ``graph.pt``, ``world_model/``, ``latent_model/``: play data, the
  representation run (checkpoints, CSV logs), the code graph, the world-model runs;
- ``log.txt``: what each command did; ``results.csv`` and ``results.md``: one row per
  evaluated method (:data:`~dorp_rl.eval.RESULT_COLUMNS`);
- ``run.lock`` (and ``running.json`` while a command runs): the run's lock, held by one
  command at a time for all of its stages (:class:`~dorp_rl.integrity.DirectoryLock`),
  so a second command on a busy run stops with exit code 2 (or waits: ``--wait``).

``--name`` is a folder strictly below ``--root``; anything else (an absolute path, ``..``
out of the root, ``""``, ``.``, a symlink elsewhere) is a usage error, as are a ``--root``
that is a file or cannot be written, a ``stages.json`` this version cannot read, stage
files replaced by others and a ``--low-level`` file that is not a world model of the
setting. A usage error (exit code 2) leaves the run folder as it was (except its lock file).

A stage whose stored config equals the current one and whose files exist is skipped (and
the command says so); a changed field re-runs that stage and every stage depending on it,
naming the fields that changed. Configs are the library's dataclasses
(:class:`~dorp_rl.trainers.RepresentationConfig`, :class:`~dorp_rl.trainers.WorldModelConfig`),
filled from the preset of ``--setting`` and overridden on the command line::

    dorp demo
    dorp train-encoder --name 1obj --setting 1obj --codes.num-steps 500
    dorp evaluate --name 1obj --setting 1obj --methods dorp vf-cem random --tasks 20
"""

from __future__ import annotations

import functools
import operator
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import torch

from dorp_rl.envs.paper import DEFAULT_SETTING
from dorp_rl.eval import SETTINGS, format_table, setting_of
from dorp_rl.integrity import DirectoryLockedError
from dorp_rl.pipeline import (
    COMMANDS,
    DEMO_CODE_STEPS,
    DORP_VARIANTS,
    LOW_LEVEL_NAMES,
    NAME_RULE,
    RUN_HOLDER,
    RUN_LOCK,
    CodeOptions,
    EvaluationOptions,
    LatentModelOptions,
    PaperOptions,
    Run,
    RunOptions,
    UsageError,
    WorldModelOptions,
    codes_stage,
    default_command,
    evaluate_stage,
    graph_stage,
    play_stage,
    quiet_torchrl,
    world_model_stage,
)
from dorp_rl.reproduce import pictures_stage, reproduce_paper, say_pictures
from dorp_rl.trainers import OfflineTrainer, TrainingGaveUpError, load_world_model

__all__ = [
    "COMMANDS",
    "DEMO_CODE_STEPS",
    "DORP_VARIANTS",
    "NAME_RULE",
    "RUN_HOLDER",
    "RUN_LOCK",
    "Run",
    "UsageError",
    "default_command",
    "main",
    "parse",
    "quiet_torchrl",
    "run_command",
]


# --------------------------------------------------------------------------- main
def _check(command: str, cmd: Any) -> None:
    """Rules between arguments that tyro cannot see; raises :class:`UsageError`.

    Each option group of the command checks its own options (``check``); the rules that
    join two groups follow here. Reads only: the run name and root
    (:func:`~dorp_rl.pipeline.run_folder`) and a ``--low-level`` checkpoint (it must be a
    world model of ``--setting``) are checked before anything is written.
    """
    groups = (RunOptions, CodeOptions, WorldModelOptions, LatentModelOptions, EvaluationOptions)
    for group in (*groups, PaperOptions):
        if isinstance(cmd, group):
            group.check(cmd, command)
    paper = isinstance(cmd, PaperOptions) and cmd.paper
    if paper and cmd.env is not None:
        raise UsageError("--env does not apply with --paper: it runs the paper's settings.")
    setting, defaults = setting_of(cmd.setting), default_command(command, cmd.setting)
    configs = {
        k: getattr(cmd, k) for k in ("codes", "world_model", "latent_model") if hasattr(cmd, k)
    }
    for key, cfg in configs.items():
        if (cfg.env, cfg.num_objects) != (setting.env, setting.num_objects):
            raise UsageError(
                f"--{key}.env {cfg.env} with --{key}.num-objects {cfg.num_objects} does not "
                f"match --setting {cmd.setting} ({setting.env}, {setting.num_objects} "
                "object(s)): choose the setting instead, it picks the presets."
            )
    for key, cfg in configs.items():
        preset = getattr(defaults, key)
        for name in OfflineTrainer.bookkeeping_fields:
            if name != "checkpoint_every" and getattr(cfg, name) != getattr(preset, name):
                option = f"--{key.replace('_', '-')}.{name.replace('_', '-')}"
                raise UsageError(
                    f"{option} is set by the run: files go to <root>/<name>/ (use --root "
                    "and --name), bars follow --progress / --no-progress and torch threads --threads."
                )
    if paper and cmd.methods != defaults.methods:
        raise UsageError(
            "--methods does not apply with --paper: it runs the methods of the "
            "paper's Table 1 in each setting (choose among them with "
            "--paper-methods, and settings with --settings)."
        )
    named = ("gt", "world-model", "latent-model")
    if isinstance(cmd, EvaluationOptions) and cmd.low_level not in named:
        if paper:
            raise UsageError(
                "--paper runs several settings: --low-level must be 'gt', 'world-model' or "
                f"'latent-model' (one model per setting), not the checkpoint {cmd.low_level!r}."
            )
        _check_world_model_file(cmd.low_level, cmd.setting)


def _check_world_model_file(path: str, setting: str) -> None:
    """``--low-level <path>`` must be a world-model checkpoint of ``setting``'s environment
    (a palette video model or a latent world model)."""
    what = (
        f"--low-level must be 'gt', 'world-model' or a world-model checkpoint file of "
        f"--setting {setting} (made by dorp train-world-model --setting {setting}, or a "
        "LatentWorldModelTrainer checkpoint)"
    )
    if not Path(path).is_file():
        raise UsageError(f"{what}; {path!r} is none of these.")
    try:
        load_world_model(path, setting_of(setting).make_env())
    except (ValueError, OSError) as err:  # another kind, env, a damaged or a text file
        raise UsageError(f"{what}: {err}") from None


def _option(argv: Sequence[str], name: str) -> str | None:
    """The value of ``--<name>`` in ``argv`` (the last one given), or ``None``."""
    value = None
    for i, arg in enumerate(argv):
        if arg == f"--{name}" and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(f"--{name}="):
            value = arg.split("=", 1)[1]
    return value


def _scan(argv: Sequence[str]) -> tuple[str | None, str]:
    """The subcommand and the setting of ``argv`` (``--env``, else ``--setting``), to fill
    in its presets; an unknown one is left to the parser (or :func:`_check`) to name."""
    command = next((a for a in argv if not a.startswith("-")), None)
    env = _option(argv, "env")
    if env is not None:
        try:
            setting_of(env)
        except ValueError:
            return command, DEFAULT_SETTING
        return command, env
    setting = _option(argv, "setting")
    return command, setting if setting in SETTINGS else DEFAULT_SETTING


def parse(argv: Sequence[str]) -> tuple[str, Any]:
    """The subcommand name and its config from ``argv`` (tyro; exit code 2 on bad arguments)."""
    import tyro

    command, setting = _scan(argv)
    if command in COMMANDS:
        # One subcommand parsed alone: its errors and help name it ("dorp evaluate").
        rest = list(argv)
        rest.remove(command)
        cmd = tyro.cli(
            COMMANDS[command],
            args=rest,
            prog=f"dorp {command}",
            default=default_command(command, setting),
        )
        if cmd.env is not None:
            cmd.setting = cmd.env  # the env's profile is the setting from here on
        return command, cmd
    choices = tuple(
        Annotated[
            cls,
            tyro.conf.subcommand(name, default=default_command(name, setting)),
        ]
        for name, cls in COMMANDS.items()
    )
    cmd = tyro.cli(
        functools.reduce(operator.or_, choices),
        args=list(argv),
        prog="dorp",
        description="DORP on TorchRL: play data, codes, code graph and planning, as stages "
        "of a run folder (<root>/<name>/). Finished stages are skipped when re-run.",
    )
    name = next(n for n, cls in COMMANDS.items() if type(cmd) is cls)
    if cmd.env is not None:
        cmd.setting = cmd.env
    return name, cmd


def run_command(name: str, cmd: Any, command_line: str | None = None) -> Path:
    """Runs a parsed command, holding the run's lock throughout; returns the run folder.

    Raises:
        UsageError: the run is busy (without ``--wait``), cannot be written, or holds
            stage records or files this command cannot use; the folder is left as it was.
    """
    torch.set_num_threads(cmd.threads)
    with Run(cmd, name, command_line=command_line) as run:
        _run_stages(run, name, cmd)
    return run.dir


def _run_stages(run: Run, name: str, cmd: Any) -> None:
    start = time.perf_counter()
    run.say(f"dorp {name}: run folder {run.dir} ({cmd.threads} thread(s))")
    if name == "collect":
        play_stage(run, cmd.codes)
    elif name == "train-encoder":
        codes_stage(run, cmd.codes)
    elif name == "build-graph":
        graph_stage(run, cmd.codes, cmd.setting)
    elif name == "train-world-model":
        world_model_stage(run, cmd.world_model)
    elif getattr(cmd, "paper", False):
        reproduce_paper(run, cmd)
    else:
        rows = evaluate_stage(run, cmd)
        pictures = pictures_stage(run, cmd)
        print(f"\n{format_table(rows)}\n")
        run.say(f"results: {run.dir / 'results.csv'}, {run.dir / 'results.md'}")
        say_pictures(run, pictures)
    run.begin_changes()
    run.say(f"dorp {name}: finished in {time.perf_counter() - start:.0f} s; files in {run.dir}")


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of the ``dorp`` console script (and ``python -m dorp_rl``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    name, cmd = parse(argv)
    if isinstance(cmd, EvaluationOptions):
        cmd.low_level = LOW_LEVEL_NAMES.get(cmd.low_level, cmd.low_level)
    try:
        if _option(argv, "env") is not None and _option(argv, "setting") is not None:
            raise UsageError(
                "--env and --setting both choose the environment: give one (--setting for "
                "the paper's settings, --env for any env profile or import path)."
            )
        _check(name, cmd)
        run_command(name, cmd, command_line=shlex.join(["dorp", *argv]))
    except (UsageError, DirectoryLockedError) as err:
        # Arguments, run folders and files that cannot be used: a message, exit code 2.
        lines = (line.strip() for line in str(err).splitlines())
        message = " ".join(line for line in lines if line)  # one line, whatever the library's
        print(f"usage: dorp {name} [-h] [OPTIONS]\ndorp {name}: error: {message}", file=sys.stderr)
        raise SystemExit(2) from None
    except TrainingGaveUpError as err:
        # A training that learned nothing: what it saw and what to change, exit code 1.
        print(f"dorp {name}: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        print(
            f"\ndorp {name}: stopped. Finished stages are kept: the same command goes on, "
            "a training from its last checkpoint, an evaluation from its last finished "
            "chunk of tasks.",
            file=sys.stderr,
        )
        raise SystemExit(130) from None  # 128 + SIGINT, as a shell reports Ctrl-C


if __name__ == "__main__":
    main()
