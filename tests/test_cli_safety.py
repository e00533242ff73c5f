"""The ``dorp`` command never loses a run's data nor writes where it should not.

One command at a time holds a run folder (two real processes on one run: the second is
refused, or waits with ``--wait``, and the first ends with the data of an uninterrupted
run); run names stay below ``--root``; a ``--root`` that is a file or cannot be written,
unreadable stage records, replaced stage files, a ``--low-level`` file that is not a
world model of the setting and a library lock held in a stage's folder each end in a
usage message (exit code 2) with the run folder left as it was.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tiny_args
import torch

from dorp_rl.cli import NAME_RULE, RUN_HOLDER, RUN_LOCK, Run, UsageError, default_command, main
from dorp_rl.data import load_play_data
from dorp_rl.integrity import DirectoryLock, DirectoryLockedError

CODES = tiny_args.CODES_ANY_FRAMES
EVAL = (*tiny_args.EVAL, "--gifs", "0")
TINY_WORLD_MODEL = tiny_args.WORLD_MODEL
#: every command, with arguments that make it tiny
COMMANDS = {
    "collect": ("collect", *CODES),
    "train-encoder": ("train-encoder", *CODES),
    "build-graph": ("build-graph", *CODES),
    "train-world-model": ("train-world-model", "--setting", "1obj", *TINY_WORLD_MODEL),
    "evaluate": ("evaluate", *CODES, *EVAL),
    "reproduce": ("reproduce", *CODES, *EVAL),
    "reproduce --paper": ("reproduce", "--paper", "--settings", "1obj", *CODES, *EVAL),
    "demo": ("demo", *CODES, *EVAL),
}


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def dorp(root: Path, *args: str, name: str = "run") -> None:
    main([*args, "--root", str(root), "--name", name, "--no-progress"])


def refused(capsys, root: Path, *args: str, name: str = "run") -> str:
    """Runs ``dorp`` expecting a usage message; returns it (one line after the usage line)."""
    with pytest.raises(SystemExit) as stop:
        dorp(root, *args, name=name)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    usage, message = err.strip().splitlines()[-2:]  # the message is one line
    assert usage.startswith(f"usage: dorp {args[0]} ") and message.startswith(
        f"dorp {args[0]}: error: "
    )
    return message


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` and its bytes (but the run's lock file, which records
    who asked for it last)."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != RUN_LOCK
    }


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """Finished runs to copy: ``graph`` (1-object play data, codes, graph), ``play2``
    (2-object play data, 320 frames) and ``wm`` (a 1-object world model)."""
    root = tmp_path_factory.mktemp("made")
    dorp(root, "build-graph", *CODES, "--codes.num-frames", "256", name="graph")
    dorp(root, "collect", "--setting", "2obj", "--codes.num-frames", "320",
         "--codes.num-envs", "16", name="play2")  # fmt: skip
    dorp(root, "train-world-model", "--setting", "1obj", *TINY_WORLD_MODEL, name="wm")
    return root


def copy_run(made: Path, name: str, root: Path) -> Path:
    shutil.copytree(made / name, root / "run", ignore=shutil.ignore_patterns(RUN_LOCK))
    return root / "run"


# --------------------------------------------------------------------------- one command at a time
def _frames(buffer) -> dict[str, torch.Tensor]:
    data = buffer[:]
    return {"/".join(k) if isinstance(k, tuple) else k: data.get(k)
            for k in data.keys(include_nested=True, leaves_only=True)}  # fmt: skip


@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="pauses a process with SIGSTOP")
def test_two_collect_commands_on_one_run_the_second_is_refused_the_first_ends_whole(
    tmp_path,
) -> None:
    run = tmp_path / "runs" / "r"
    frames = (20000, 10000)  # the two commands differ in --codes.num-frames
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    procs = {
        n: subprocess.Popen(
            [
                sys.executable,
                "-m",
                "dorp_rl",
                "collect",
                "--root",
                str(tmp_path / "runs"),
                "--name",
                "r",
                "--setting",
                "1obj",
                "--codes.num-envs",
                "16",
                "--codes.num-frames",
                str(n),
                "--no-progress",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )  # fmt: skip
        for n in frames
    }
    try:
        # Started together: the one that takes the run's lock first (and has recorded its
        # command) is paused while it collects, so that the other certainly finds it busy.
        by_pid = {p.pid: n for n, p in procs.items()}
        deadline = time.monotonic() + 300
        first = None
        while first is None:
            assert time.monotonic() < deadline, "no command took the run's lock"
            try:
                pids = {json.loads((run / f).read_text())["pid"] for f in (RUN_LOCK, RUN_HOLDER)}
                first = by_pid.get(pids.pop()) if len(pids) == 1 else None
            except (OSError, ValueError):
                pass
            time.sleep(0.002)
        os.kill(procs[first].pid, signal.SIGSTOP)
        assert procs[first].poll() is None
        with pytest.raises(DirectoryLockedError):  # paused while holding the lock
            DirectoryLock(run, RUN_LOCK).acquire()
        second = next(n for n in frames if n != first)
        out, err = procs[second].communicate(timeout=300)
        assert procs[second].returncode == 2, err
        message = err.strip().splitlines()[-1]
        assert message.startswith(
            f"dorp collect: error: the run folder {run} is in use by process {procs[first].pid} on "
        )
        assert f"dorp collect --root {tmp_path / 'runs'} --name r" in message  # its command
        assert f"--codes.num-frames {first}" in message and "add --wait" in message
        assert "Traceback" not in err and out == ""  # refused before saying anything
        os.kill(procs[first].pid, signal.SIGCONT)
        out, err = procs[first].communicate(timeout=300)
        assert procs[first].returncode == 0, err
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGCONT)
                proc.kill()
                proc.wait()
    assert "play: done in" in out
    # The first one's data are those of an uninterrupted run; the second left no trace.
    dorp(tmp_path, "collect", "--setting", "1obj", "--codes.num-envs", "16",
         "--codes.num-frames", str(first), name="whole")  # fmt: skip
    got, whole = (_frames(load_play_data(d / "play")) for d in (run, tmp_path / "whole"))
    assert got.keys() == whole.keys() and len(got["pixels"]) == first
    assert all(torch.equal(got[k], whole[k]) for k in got)
    stages = json.loads((run / "stages.json").read_text())
    assert stages["play"]["config"]["num_frames"] == first
    assert json.loads((run / "config.json").read_text())["codes"]["num_frames"] == first
    log = (run / "log.txt").read_text()
    assert log.count("dorp collect: run folder") == 1 and str(second) not in log
    assert not (run / RUN_HOLDER).exists()


def test_wait_waits_for_the_run_to_be_free_then_goes_on(tmp_path) -> None:
    run = tmp_path / "run"
    holder = DirectoryLock(run, RUN_LOCK).acquire()  # this process: a command on the run
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "dorp_rl", "collect", "--root", str(tmp_path), "--name", "run",
         *CODES, "--codes.num-frames", "256", "--no-progress", "--wait"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        first = proc.stdout.readline()
        assert first.startswith(f"the run folder {run} is in use by process {os.getpid()} on ")
        assert first.rstrip().endswith("; waiting (--wait)")
        time.sleep(1.0)
        assert proc.poll() is None and not (run / "stages.json").exists()  # still waiting
    finally:
        holder.release()
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert "play: running (not run yet)" in out and "play: done in" in out
    assert json.loads((run / "stages.json").read_text())["play"]["config"]["num_frames"] == 256


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_is_refused_on_a_busy_run(tmp_path, capsys, command) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "stages.json").write_text("{}\n")
    lock = DirectoryLock(run, RUN_LOCK).acquire()
    holder = {"pid": os.getpid(), "command": "dorp demo --name run"}
    (run / RUN_HOLDER).write_text(json.dumps(holder))
    before = snapshot(run)
    try:
        message = refused(capsys, tmp_path, *COMMANDS[command])
    finally:
        lock.release()
    assert f"the run folder {run} is in use by process {os.getpid()} on " in message
    assert "(dorp demo --name run, since " in message  # the command it recorded
    assert snapshot(run) == before


def test_a_command_refused_just_after_another_took_the_lock_names_its_command(
    tmp_path, capsys
) -> None:
    # The holder writes running.json a moment after it takes run.lock: a refused command
    # that looks in between still names the holder's command.
    import threading

    run = tmp_path / "run"
    lock = DirectoryLock(run, RUN_LOCK).acquire()
    holder = {"pid": os.getpid(), "command": "dorp collect --name run"}
    late = threading.Timer(0.3, lambda: (run / RUN_HOLDER).write_text(json.dumps(holder)))
    late.start()
    try:
        message = refused(capsys, tmp_path, *COMMANDS["collect"])
    finally:
        late.join()
        lock.release()
    assert f"the run folder {run} is in use by process {os.getpid()} on " in message
    assert "(dorp collect --name run, since " in message


def test_a_busy_sub_run_of_reproduce_paper_is_refused(tmp_path, capsys) -> None:
    sub = tmp_path / "run" / "1obj"
    lock = DirectoryLock(sub, RUN_LOCK).acquire()
    try:
        message = refused(capsys, tmp_path, *COMMANDS["reproduce --paper"])
    finally:
        lock.release()
    assert f"the run folder {sub} is in use by process {os.getpid()}" in message
    assert snapshot(tmp_path) == {}  # the run above is left as it was too


def test_every_stage_of_every_command_holds_the_run_lock(tmp_path, monkeypatch, capsys) -> None:
    checked: list[tuple[str, str]] = []
    stage = Run.stage

    def locked_stage(self, name, *args, **kwargs):
        with pytest.raises(DirectoryLockedError):  # held by this command, not free
            DirectoryLock(self.dir, RUN_LOCK).acquire()
        if self.dir.parent != tmp_path:  # a sub-run: the run above is held as well
            with pytest.raises(DirectoryLockedError):
                DirectoryLock(self.dir.parent, RUN_LOCK).acquire()
        checked.append((self.dir.name, name))
        return stage(self, name, *args, **kwargs)

    monkeypatch.setattr(Run, "stage", locked_stage)
    dorp(tmp_path, *COMMANDS["demo"], "--codes.num-frames", "256", name="demo")
    assert checked == [("demo", s) for s in ("play", "codes", "graph", "evaluate:dorp:gt",
                       "evaluate:vf-cem:gt", "pictures", "play", "codes", "graph")]  # fmt: skip
    checked.clear()
    dorp(tmp_path, *COMMANDS["reproduce --paper"], "--paper-methods", "vf-rs", name="paper")
    assert checked == [("1obj", "evaluate:vf-rs:gt")]
    for run in (tmp_path / "demo", tmp_path / "paper", tmp_path / "paper" / "1obj"):
        DirectoryLock(run, RUN_LOCK).acquire().release()  # free again at the end


# --------------------------------------------------------------------------- run names
OUTSIDE = "../outside"


@pytest.mark.parametrize(
    ("name", "why"),
    [
        (OUTSIDE, "outside --root"),
        ("../../escape", "outside --root"),
        ("a/../../outside", "outside --root"),
        ("ABSOLUTE", "is an absolute path"),
        ("", "is empty"),
        ("  ", "is empty"),
        (".", "--root itself"),
        ("a/..", "--root itself"),
        ("link-out", "outside --root"),
        ("link-root", "--root itself"),
    ],
)
def test_a_name_that_is_not_a_folder_below_the_root_is_refused(tmp_path, capsys, name, why) -> None:
    root, outside = tmp_path / "a" / "runs", tmp_path / "a" / "outside"
    root.mkdir(parents=True)
    (root / "link-out").symlink_to(outside, target_is_directory=True)
    (root / "link-root").symlink_to(root, target_is_directory=True)
    name = str(tmp_path / "abs") if name == "ABSOLUTE" else name
    message = refused(capsys, root, *COMMANDS["collect"], name=name)
    assert f"--name {name!r} " in message and why in message and NAME_RULE in message
    assert sorted(p.name for p in root.iterdir()) == ["link-out", "link-root"]  # nothing new
    assert not outside.exists() and not (tmp_path / "abs").exists()
    made = sorted(os.path.relpath(os.path.join(d, n), tmp_path)
                  for d, dirs, files in os.walk(tmp_path) for n in dirs + files)  # fmt: skip
    assert made == ["a", "a/runs", "a/runs/link-out", "a/runs/link-root"]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_refuses_a_name_out_of_the_root(tmp_path, capsys, command) -> None:
    root = tmp_path / "runs"
    message = refused(capsys, root, *COMMANDS[command], name=OUTSIDE)
    assert "outside --root" in message
    assert not any(tmp_path.iterdir())  # not even the root was made


def test_a_run_made_in_python_checks_its_name_too(tmp_path) -> None:
    cmd = default_command("collect", "1obj")
    cmd.root, cmd.name = str(tmp_path), "../elsewhere"
    with pytest.raises(UsageError, match="outside --root"):
        Run(cmd, "collect")
    assert not any(tmp_path.parent.glob("elsewhere"))


# --------------------------------------------------------------------------- roots
def test_a_root_that_is_a_file_is_refused(tmp_path, capsys) -> None:
    root = tmp_path / "runs.txt"
    root.write_text("not a folder\n")
    for given in (root, root / "below"):
        message = refused(capsys, given, *COMMANDS["collect"])
        assert f"--root {given}: {root} is a file, not a folder" in message
    assert root.read_text() == "not a folder\n" and sorted(tmp_path.iterdir()) == [root]


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes anyway")
def test_a_root_that_cannot_be_written_is_refused(tmp_path, capsys) -> None:
    root = tmp_path / "runs"
    root.mkdir()
    root.chmod(0o555)
    try:
        message = refused(capsys, root, *COMMANDS["collect"])
    finally:
        root.chmod(0o755)
    assert f"cannot write in the run folder {root / 'run'}: Permission denied" in message
    assert not any(root.iterdir())


@pytest.mark.parametrize("fresh", [True, False])
def test_a_read_only_file_system_is_refused(tmp_path, made, capsys, monkeypatch, fresh) -> None:
    """As the OS reports a read-only mount (EROFS): for a new run and for an existing one."""
    run = tmp_path / "run" if fresh else copy_run(made, "graph", tmp_path)
    before = snapshot(tmp_path)

    def read_only(self, *args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self.path))

    monkeypatch.setattr(DirectoryLock, "acquire", read_only)
    message = refused(capsys, tmp_path, *COMMANDS["build-graph"], "--codes.num-frames", "256")
    assert f"cannot write in the run folder {run}: {os.strerror(errno.EROFS)}" in message
    assert "Use a --root you can write in" in message
    assert snapshot(tmp_path) == before


# --------------------------------------------------------------------------- run folders
@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ('{"play": {"config": ', "it is not JSON"),
        ("", "it is empty"),
        ("[]", "it holds a list, not a record per stage"),
        ('"play"', "it holds a str, not a record per stage"),
        ("STAGES_WITHOUT_CONFIG", "stage 'codes' has no 'config' mapping"),
        ('{"play": "done"}', "stage 'play' has no 'config' mapping"),
        ('{"play": {"config": [1]}}', "stage 'play' has no 'config' mapping"),
        (
            '{"evaluate:vf-rs:gt": {"config": {}, "seconds": 1}}',
            "finished stage 'evaluate:vf-rs:gt' has no 'summary' mapping",
        ),
        (
            '{"play": {"config": null, "seconds": "long"}}',
            "stage 'play' has 'seconds' 'long', not a number",
        ),
    ],
)
@pytest.mark.parametrize("command", ["build-graph", "evaluate"])
def test_stage_records_that_cannot_be_read_are_refused(
    tmp_path, made, capsys, content, problem, command
) -> None:
    run = copy_run(made, "graph", tmp_path)
    stages = run / "stages.json"
    if content == "STAGES_WITHOUT_CONFIG":
        records = json.loads(stages.read_text())
        del records["codes"]["config"]
        content = json.dumps(records)
    stages.write_text(content)
    before = snapshot(run)
    message = refused(capsys, tmp_path, *COMMANDS[command], "--codes.num-frames", "256")
    assert f"{stages} cannot be read as this run's stage records: {problem}" in message
    assert "Remove it to run every stage again, or use another --name." in message
    assert snapshot(run) == before
    DirectoryLock(run, RUN_LOCK).acquire().release()  # and the lock is free again


def _other_setting(run: Path, made: Path) -> None:
    shutil.rmtree(run / "play")
    shutil.copytree(made / "play2" / "play", run / "play")


def _scrambled(run: Path, made: Path) -> None:
    for i, path in enumerate(sorted(p for p in (run / "play").rglob("*") if p.is_file())):
        path.write_bytes(torch.randint(0, 256, (path.stat().st_size,), generator=torch.Generator().manual_seed(i), dtype=torch.uint8).numpy().tobytes())  # fmt: skip


def _foreign_storage(run: Path, made: Path) -> None:
    shutil.rmtree(run / "play")
    (run / "play" / "storage").mkdir(parents=True)
    (run / "play" / "storage" / "notes.txt").write_text("someone else's files\n")


def _graph_of_bytes(run: Path, made: Path) -> None:
    (run / "graph.pt").write_bytes(b"\x00not a graph" * 100)


@pytest.mark.parametrize(
    ("swap", "folder", "why"),
    [
        (_other_setting, "play", "num_frames"),
        (_scrambled, "play", "play data"),
        (_foreign_storage, "play", "did not write"),
        (_graph_of_bytes, "graph.pt", "graph"),
    ],
)
def test_stage_files_replaced_by_others_are_refused_untouched(
    tmp_path, made, capsys, swap, folder, why
) -> None:
    run = copy_run(made, "graph", tmp_path)
    swap(run, made)
    before = snapshot(run)
    message = refused(capsys, tmp_path, *COMMANDS["build-graph"], "--codes.num-frames", "256")
    stage = folder.removesuffix(".pt")
    assert message.startswith(
        f"dorp build-graph: error: {run / folder} does not hold what stage {stage} made: "
    )
    assert why in message and message.endswith("Remove it to make it again, or use another --name.")
    assert snapshot(run) == before


def test_a_library_lock_in_a_stage_folder_is_refused_before_anything_is_removed(
    tmp_path, capsys
) -> None:
    from dorp_rl.data.play import _LOCK_FILE

    play = tmp_path / "run" / "play"
    collecting = DirectoryLock(play, _LOCK_FILE).acquire()  # a collection of another process
    (play / "storage").mkdir()
    (play / "storage" / "part.memmap").write_bytes(b"\x01" * 64)
    before = snapshot(tmp_path)
    try:
        message = refused(capsys, tmp_path, *COMMANDS["collect"])
    finally:
        collecting.release()
    assert f"{play} is being written by process {os.getpid()}" in message
    assert snapshot(tmp_path) == before  # play/ kept, no stage recorded


# --------------------------------------------------------------------------- --low-level
def _encoder(made: Path, tmp_path: Path) -> Path:
    return made / "graph" / "codes" / "checkpoints" / "last.pt"


def _world_model_1obj(made: Path, tmp_path: Path) -> Path:
    return made / "wm" / "world_model" / "checkpoints" / "last.pt"


def _text(made: Path, tmp_path: Path) -> Path:
    (tmp_path / "model.pt").write_text("a world model, honestly\n")
    return tmp_path / "model.pt"


@pytest.mark.parametrize(
    ("checkpoint", "setting", "why"),
    [
        (_encoder, "1obj", "holds a 'representation' model, expected 'world_model'"),
        (_world_model_1obj, "2obj", "was trained on another environment"),
        (_text, "1obj", "is corrupted or not a torch file"),
    ],
)
@pytest.mark.parametrize("command", ["evaluate", "reproduce", "demo"])
def test_a_low_level_file_that_is_not_a_world_model_of_the_setting_is_refused_up_front(
    tmp_path, made, capsys, checkpoint, setting, why, command
) -> None:
    path = checkpoint(made, tmp_path)
    args = (
        command,
        "--setting",
        setting,
        "--codes.num-envs",
        "16",
        *EVAL,
        "--low-level",
        str(path),
    )
    message = refused(capsys, tmp_path / "runs", *args)
    assert (
        f"--low-level must be 'gt', 'world-model' or a world-model checkpoint file of --setting {setting}"
        in message
    )
    assert why in message and str(path) in message
    assert not (tmp_path / "runs").exists()  # no stage ran: nothing was written


def test_a_world_model_of_the_setting_is_still_taken(tmp_path, made, capsys) -> None:
    path = _world_model_1obj(made, tmp_path)
    dorp(tmp_path, *COMMANDS["evaluate"], "--methods", "vf-rs", "--low-level", str(path))
    assert "evaluate:vf-rs:checkpoint: done in" in capsys.readouterr().out
