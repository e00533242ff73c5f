"""Directory locks: one writer per directory, a clear error (or a wait) for the second.

Covers :class:`~dorp_rl.integrity.DirectoryLock` itself, two real processes collecting
into one play-data directory, a collection killed with SIGKILL (the OS drops its lock,
and collecting again redoes it), and two trainings in one ``out_dir``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

import dorp_rl.data.play as play_module
from dorp_rl.data import PLAY_KEYS, collect_play_data, load_play_data
from dorp_rl.envs import KeyWallEnv
from dorp_rl.integrity import DirectoryLock, DirectoryLockedError
from dorp_rl.trainers import RepresentationTrainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

LOCK = "play_data.lock"


def collect(directory: Path, num_frames: int, **kwargs) -> object:
    return collect_play_data(
        KeyWallEnv(batch_size=(4,)),
        num_frames,
        directory=directory,
        seed=0,
        trajectory_length=50,
        **kwargs,
    )


def start_collector(directory: Path, num_frames: int) -> subprocess.Popen:
    """Another process collecting into ``directory`` (returns once it holds the lock)."""
    code = (
        "import torch; torch.set_num_threads(1)\n"
        "from dorp_rl.envs import KeyWallEnv\n"
        "from dorp_rl.data import collect_play_data\n"
        f"collect_play_data(KeyWallEnv(batch_size=(4,)), {num_frames}, directory={str(directory)!r},"
        " seed=0, trajectory_length=50)\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    process = subprocess.Popen([sys.executable, "-c", code], env=env, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (directory / "storage").exists():
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"collector did not start: {process.stderr.read().decode()[-2000:]}")
        time.sleep(0.05)
    return process


def stored(buffer) -> dict:
    data = buffer[: len(buffer)]
    return {key: data.get(key) for key in PLAY_KEYS}


# ---------------------------------------------------------------- the lock itself
def test_a_second_holder_is_refused_with_the_holder_and_lock_file(tmp_path):
    first = DirectoryLock(tmp_path, "x.lock", purpose="testing").acquire()
    with pytest.raises(DirectoryLockedError) as info:
        DirectoryLock(tmp_path, "x.lock").acquire()
    message = str(info.value)
    assert isinstance(info.value, ValueError)
    assert f"process {os.getpid()}" in message and str(tmp_path / "x.lock") in message
    first.release()
    DirectoryLock(tmp_path, "x.lock").acquire().release()  # free again


def test_a_bounded_wait_gives_up_after_its_time(tmp_path):
    held = DirectoryLock(tmp_path).acquire()
    start = time.monotonic()
    with pytest.raises(DirectoryLockedError):
        DirectoryLock(tmp_path).acquire(wait=0.3, poll=0.05)
    assert time.monotonic() - start >= 0.3
    held.release()


def test_wait_true_returns_once_the_holder_releases(tmp_path):
    held = DirectoryLock(tmp_path).acquire()
    threading.Timer(0.3, held.release).start()
    start = time.monotonic()
    second = DirectoryLock(tmp_path).acquire(wait=True, poll=0.05)
    assert second.held and time.monotonic() - start >= 0.25
    second.release()


# ---------------------------------------------------------------- play data
def test_collecting_into_a_locked_directory_fails_without_touching_it(tmp_path):
    directory = tmp_path / "busy"
    directory.mkdir()
    holder = DirectoryLock(directory, LOCK).acquire()
    with pytest.raises(DirectoryLockedError, match="being written"):
        collect(directory, 400)
    assert not (directory / "storage").exists()
    holder.release()
    assert len(collect(directory, 400)) == 400


def test_two_processes_never_mix_their_rows(tmp_path):
    directory = tmp_path / "shared"
    other = start_collector(directory, 40_000)
    try:
        with pytest.raises(DirectoryLockedError, match=f"process {other.pid}"):
            collect(directory, 2000)  # another size: its rows would differ from the first's
        assert other.poll() is None  # the first collection was not disturbed
        assert other.wait(timeout=300) == 0
    finally:
        other.kill()
        other.wait()
    # every stored row is the first collection's, as if it had run alone
    data = stored(load_play_data(directory))
    reference = stored(collect(tmp_path / "reference", 40_000))
    for key in PLAY_KEYS:
        assert torch.equal(data[key], reference[key]), key


def test_a_killed_collection_leaves_no_stale_lock_and_is_redone(tmp_path):
    directory = tmp_path / "killed"
    other = start_collector(directory, 400_000)
    other.send_signal(signal.SIGKILL)
    other.wait()
    assert (directory / LOCK).exists() and not (directory / "play_data.json").exists()
    data = stored(collect(directory, 2000))  # the OS dropped the lock; ours to redo
    reference = stored(collect(tmp_path / "reference", 2000))
    for key in PLAY_KEYS:
        assert torch.equal(data[key], reference[key]), key


def test_wait_loads_what_the_other_process_collected(tmp_path, monkeypatch):
    directory = tmp_path / "wait"
    other = start_collector(directory, 4000)

    def refuse(*args, **kwargs):
        raise AssertionError("collected instead of loading the other process's data")

    monkeypatch.setattr(play_module, "Collector", refuse)
    data = stored(collect(directory, 4000, wait=True))
    assert other.wait(timeout=120) == 0
    reference = stored(load_play_data(directory))
    for key in PLAY_KEYS:
        assert torch.equal(data[key], reference[key]), key


# ---------------------------------------------------------------- training
def test_two_trainings_in_one_out_dir_are_refused(representation_config):
    cfg = representation_config(num_steps=2)
    trainer = RepresentationTrainer(cfg)
    holder = DirectoryLock(cfg.out_dir, ".train.lock").acquire()
    with pytest.raises(DirectoryLockedError, match="representation training"):
        trainer.train()
    assert not trainer.checkpoint_path.exists()
    holder.release()
    assert trainer.train()["step"] == 2
