"""Fixtures shared by the tests: tiny trainer configs, tiny ``dorp`` runs, single-threaded torch."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import tiny_args
import torch

from dorp_rl.modules import VideoModelConfig
from dorp_rl.trainers import RepresentationConfig, WorldModelConfig


class TinyConfigs:
    """Trainer configs of a few seconds each (1-object rearrangement)."""

    @staticmethod
    def representation(out_dir: str | Path, **overrides: Any) -> RepresentationConfig:
        base = RepresentationConfig.for_env(
            "rearrangement",
            1,
            encoder={"code_sizes": (8,)},
            num_frames=256,
            num_envs=16,
            batch_size=32,
            num_steps=10,
            log_every=2,
            checkpoint_every=5,
            diagnostics_every=10**9,
            progress=False,
            out_dir=str(out_dir),
            collapse_check_after=10**9,
            dead_check_frames=0,
        )
        return base.replace(**overrides)

    @staticmethod
    def world_model(out_dir: str | Path, **overrides: Any) -> WorldModelConfig:
        base = WorldModelConfig.for_env(
            "rearrangement",
            1,
            num_steps=6,
            num_frames=256,
            num_envs=16,
            horizon=3,
            trajectory_length=4,
            eval_frames=128,
            eval_sequences=8,
            model=VideoModelConfig.small(),
            batch_size=8,
            log_every=2,
            checkpoint_every=2,
            eval_every=10**6,
            progress=False,
            out_dir=str(out_dir),
        )
        return base.replace(**overrides)


@pytest.fixture(scope="session")
def tiny_configs() -> type[TinyConfigs]:
    return TinyConfigs


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """Tiny tensors: thread hand-offs cost more than they save (far more on a busy 2-core
    machine); one torch thread for the module, the count restored after. A module asks for
    it with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def representation_config(tmp_path) -> Callable[..., RepresentationConfig]:
    """``make(name="run", **overrides)``: a tiny representation config under ``tmp_path``."""
    return lambda name="run", **overrides: TinyConfigs.representation(tmp_path / name, **overrides)


@pytest.fixture
def world_model_config(tmp_path) -> Callable[..., WorldModelConfig]:
    """``make(name="wm", **overrides)``: a tiny world-model config under ``tmp_path``."""
    return lambda name="wm", **overrides: TinyConfigs.world_model(tmp_path / name, **overrides)


class DorpCommand:
    """Runs the ``dorp`` command in a test; ``CODES`` and ``EVAL`` are arguments of seconds."""

    CODES = tiny_args.CODES
    EVAL = tiny_args.EVAL

    def __init__(self, capsys: pytest.CaptureFixture[str]) -> None:
        self.capsys = capsys

    def __call__(self, root: Path, command: str, *args: str, name: str = "run") -> str:
        """Runs ``dorp <command> <args>`` in ``root/name`` without progress bars; returns
        what it printed."""
        from dorp_rl.cli import main

        main([command, "--root", str(root), "--name", name, "--no-progress", *args])
        return self.capsys.readouterr().out


@pytest.fixture
def dorp(capsys) -> DorpCommand:
    """``dorp(root, command, *args, name="run")``: the ``dorp`` command, printing captured."""
    return DorpCommand(capsys)
