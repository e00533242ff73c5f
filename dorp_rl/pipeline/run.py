"""A run folder ``<root>/<name>/`` (:class:`Run`): its lock, its stage cache
(``stages.json``: a stage whose stored config matches is skipped, a stopped one resumes)
and its log.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dorp_rl.integrity import DirectoryLock, DirectoryLockedError, atomic_write_bytes
from dorp_rl.trainers import (
    OfflineTrainer,
    RepresentationConfig,
    WorldModelConfig,
)

__all__ = [
    "stage_config",
    "NAME_RULE",
    "RUN_HOLDER",
    "RUN_LOCK",
    "Run",
    "UsageError",
    "quiet_torchrl",
    "run_folder",
]


#: the run folder's lock file (one command at a time in a run folder)
RUN_LOCK = "run.lock"


#: which command holds the run's lock (pid and command line), for the refusal's message
RUN_HOLDER = "running.json"


#: what a run name is, for the usage messages
NAME_RULE = "a run name is a folder below --root, such as 'demo' or 'paper/2obj'"


# --------------------------------------------------------------------------- runs and stages
class UsageError(ValueError):
    """Arguments that do not fit together (reported as a usage error, exit code 2)."""


def stage_config(cfg: Any) -> dict[str, Any]:
    """A trainer config as a stage stores it: without the fields that never change its
    result (paths, progress)."""
    return {k: v for k, v in cfg.to_dict().items() if k not in OfflineTrainer.bookkeeping_fields}


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
                return json.loads(json.dumps(stage_config(cls.from_dict(values))))
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
