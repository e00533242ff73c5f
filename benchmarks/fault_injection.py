"""Deliberate mistakes and faults against the public API, and how each one ends.

Every fault is something a user (or a crash, a disk, a second process) can do: damage a
play buffer or a checkpoint, pass a wrong config value, feed a wrong tensor. Each is
run once and classified:

- ``clear``: the expected error type (``ValueError`` or ``FileNotFoundError``, or a
  subclass) with a message that names the cause (every listed word appears in it);
- ``handled``: a fault the library is meant to take (e.g. numpy frames), with a correct
  result;
- ``unclear``: an error of another type, or one whose message does not name the cause
  (a traceback from deep inside torch or tensordict);
- ``silent``: no error and a wrong result, an ignored setting, or damaged data on disk.

Only API that existed before the reliability work is used, so the same list measures an
older checkout too (``PYTHONPATH=<checkout> python benchmarks/fault_injection.py``).

```bash
.venv/bin/python benchmarks/fault_injection.py --threads 1            # about a minute
.venv/bin/python benchmarks/fault_injection.py --json faults.json --show silent unclear
```
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import multiprocessing as mp
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from bench_threads import add_threads_argument, parse_with_threads
from tensordict import TensorDict

from dorp_rl.data import collect_play_data, load_play_data
from dorp_rl.envs import (
    GroundTruthModelEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    VideoModelEnv,
)
from dorp_rl.eval import evaluate_policy, make_task_set
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.modules.video import VideoModelConfig, VideoPredictionModel
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeMatchCost,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import VisualForesightPolicy
from dorp_rl.trainers import (
    RepresentationConfig,
    RepresentationTrainer,
    WorldModelConfig,
    WorldModelTrainer,
    load_encoder,
    load_video_model,
)

_ROOT: list[Path] = []


def root() -> Path:
    """The scratch folder of this run (made on first use: a spawned child imports this file)."""
    if not _ROOT:
        _ROOT.append(Path(tempfile.mkdtemp(prefix="dorp_faults_")))
    return _ROOT[0]


class Silent(Exception):
    """Raised by a fault's own check: no error, and the result is wrong."""


@dataclasses.dataclass
class Fault:
    category: str
    name: str
    run: Callable[[], Any]
    #: words a clear error message holds (``None``: no error is acceptable)
    words: tuple[str, ...] | None
    errors: tuple[type[BaseException], ...] = (ValueError,)
    #: whether taking the input (with a correct result) is as good as a clear error
    may_handle: bool = False


FAULTS: list[Fault] = []
#: what a fault's ``run`` returns when the fault turned out to change nothing
HARMLESS = "harmless"


def fault(
    category: str,
    name: str,
    words: tuple[str, ...] | None,
    errors: tuple[type[BaseException], ...] = (ValueError,),
    may_handle: bool = False,
):
    def register(fn: Callable[[], Any]) -> Callable[[], Any]:
        FAULTS.append(Fault(category, name, fn, words, errors, may_handle))
        return fn

    return register


def fresh(name: str) -> Path:
    path = root() / f"{name}-{time.perf_counter_ns()}"
    return path


# ------------------------------------------------------------------ shared fixtures
def play_dir(**kwargs: Any) -> Path:
    """A small complete key-wall collection in a fresh copy of a directory."""
    key = json.dumps(kwargs, sort_keys=True)
    source = root() / f"play-{abs(hash(key))}"
    if not source.exists():
        env = KeyWallEnv(batch_size=(kwargs.get("num_envs", 2),))
        collect_play_data(
            env, kwargs.get("num_frames", 200), directory=source, seed=0, trajectory_length=10
        )
    target = fresh("play")
    shutil.copytree(source, target)
    return target


def load_dir(directory: Path) -> Any:
    return load_play_data(directory)


def rep_config(**overrides: Any) -> RepresentationConfig:
    base = RepresentationConfig.for_env(
        "rearrangement",
        1,
        encoder={"code_sizes": (8,)},
        num_frames=256,
        num_envs=16,
        batch_size=32,
        num_steps=6,
        log_every=3,
        checkpoint_every=3,
        diagnostics_every=10**9,
        progress=False,
        out_dir=str(fresh("rep")),
        collapse_check_after=10**9,
    )
    return base.replace(**overrides)


def wm_config(**overrides: Any) -> WorldModelConfig:
    base = WorldModelConfig.for_env(
        "rearrangement",
        1,
        num_steps=4,
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
        out_dir=str(fresh("wm")),
    )
    return base.replace(**overrides)


_CHECKPOINTS: dict[str, Path] = {}


def checkpoint(kind: str) -> Path:
    """A fresh copy of a trained tiny checkpoint (``"rep"`` or ``"wm"``)."""
    if kind not in _CHECKPOINTS:
        trainer = (
            RepresentationTrainer(rep_config()) if kind == "rep" else WorldModelTrainer(wm_config())
        )
        trainer.train()
        _CHECKPOINTS[kind] = trainer.checkpoint_path
    target = fresh(f"ckpt-{kind}") / "checkpoints" / "last.pt"
    target.parent.mkdir(parents=True)
    shutil.copy(_CHECKPOINTS[kind], target)
    return target


def weights(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in module.state_dict().items()}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def flip(path: Path, fraction: float) -> None:
    data = bytearray(path.read_bytes())
    position = min(len(data) - 1, int(len(data) * fraction))
    data[position] ^= 0xFF
    path.write_bytes(bytes(data))


def legacy_checkpoint(kind: str, edit: Callable[[dict], None]) -> Path:
    """A checkpoint rewritten as the plain (pre-checksum) payload after ``edit``."""
    from dorp_rl.checkpoint import load_checkpoint

    path = checkpoint(kind)
    payload = load_checkpoint(path)
    payload["format"] = 1
    edit(payload)
    torch.save(payload, path)
    return path


# ------------------------------------------------------------------ data on disk
def damaged_buffer(action: Callable[[Path], None]) -> Callable[[], Any]:
    def run() -> Any:
        directory = play_dir()
        action(directory)
        before = {p: p.stat().st_size for p in directory.rglob("*.memmap")}
        try:
            buffer = load_dir(directory)
            data = buffer[: len(buffer)]
            data.get(("next", "pixels"))
            if data.get(("next", "pixels"), None) is None:
                raise Silent("loaded without ('next', 'pixels')")
            raise Silent("a damaged buffer loaded")
        finally:
            after = {p: p.stat().st_size for p in directory.rglob("*.memmap")}
            if before != after:
                raise Silent("loading changed the size of data files")

    return run


def _truncate(name: str) -> Callable[[Path], None]:
    def act(directory: Path) -> None:
        path = directory / "storage" / name
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])

    return act


def _flip(name: str, fraction: float) -> Callable[[Path], None]:
    return lambda directory: flip(directory / "storage" / name, fraction)


def _delete(name: str) -> Callable[[Path], None]:
    def act(directory: Path) -> None:
        target = directory / "storage" / name
        shutil.rmtree(target) if target.is_dir() else target.unlink()

    return act


def _append(name: str) -> Callable[[Path], None]:
    def act(directory: Path) -> None:
        with open(directory / "storage" / name, "ab") as handle:
            handle.write(b"\x00" * 768)

    return act


for _name, _act, _words in [
    ("truncated pixels.memmap", _truncate("pixels.memmap"), ("pixels.memmap",)),
    ("truncated next/pixels.memmap", _truncate("next/pixels.memmap"), ("pixels.memmap",)),
    ("truncated action.memmap", _truncate("action.memmap"), ("action.memmap",)),
    ("flipped byte in pixels.memmap", _flip("pixels.memmap", 0.5), ("pixels.memmap",)),
    ("flipped byte in next/pixels.memmap", _flip("next/pixels.memmap", 0.3), ("pixels.memmap",)),
    ("flipped byte in action.memmap", _flip("action.memmap", 0.5), ("action.memmap",)),
    ("flipped byte in state.memmap", _flip("state.memmap", 0.2), ("state.memmap",)),
    ("flipped byte in traj_id.memmap", _flip("traj_id.memmap", 0.7), ("traj_id.memmap",)),
    ("deleted storage/next", _delete("next"), ("next",)),
    ("deleted state.memmap", _delete("state.memmap"), ("state",)),
    ("bytes appended to pixels.memmap", _append("pixels.memmap"), ("pixels.memmap",)),
]:
    FAULTS.append(Fault("data", _name, damaged_buffer(_act), _words))


def _mismatch(change: dict[str, Any], words: tuple[str, ...]) -> None:
    def run() -> Any:
        directory = play_dir()
        kwargs = {"num_envs": 2, "num_frames": 200, "seed": 0, "trajectory_length": 10} | change
        env = KeyWallEnv(batch_size=(kwargs.pop("num_envs"),))
        if kwargs.pop("objects", None):
            env = ObjectRearrangementEnv(num_objects=2, batch_size=env.batch_size)
        collect_play_data(env, kwargs.pop("num_frames"), directory=directory, **kwargs)
        raise Silent("returned the stored data collected with other arguments")

    FAULTS.append(Fault("data", f"reuse with other {'/'.join(change)}", run, words))


_mismatch({"num_envs": 4}, ("num_envs",))
_mismatch({"seed": 1}, ("seed",))
_mismatch({"num_frames": 100}, ("num_frames",))
_mismatch({"trajectory_length": 5}, ("trajectory_length",))
_mismatch({"objects": True}, ("env",))


@fault("data", "pre-existing storage/ folder of the user", ("storage",))
def _user_storage() -> Any:
    directory = fresh("user")
    (directory / "storage").mkdir(parents=True)
    mine = directory / "storage" / "thesis.txt"
    mine.write_text("not play data")
    try:
        collect_play_data(KeyWallEnv(batch_size=(2,)), 50, directory=directory, seed=0)
    finally:
        if not mine.exists():
            raise Silent("the user's file was deleted")
    raise Silent("collected over the user's folder")


@fault("data", "metadata seed edited (bit flip 0 -> 1), then seed=1 requested", ("play_data",))
def _metadata_flip() -> Any:
    directory = play_dir()
    meta = directory / "play_data.json"
    meta.write_text(meta.read_text().replace('"seed": 0', '"seed": 1'))
    collect_play_data(
        KeyWallEnv(batch_size=(2,)), 200, directory=directory, seed=1, trajectory_length=10
    )
    raise Silent("seed-0 data returned for seed 1")


@fault("data", "truncated play_data.json", ("play_data.json",))
def _metadata_truncated() -> Any:
    directory = play_dir()
    meta = directory / "play_data.json"
    meta.write_text(meta.read_text()[:40])
    load_dir(directory)


@fault("data", "extending a loaded buffer writes into the stored data", None)
def _extend_loaded() -> Any:
    directory = play_dir()
    original = load_dir(directory)[:200]["pixels"].clone()
    buffer = load_dir(directory)
    extra = buffer[:5].exclude("index").clone()
    extra["pixels"] = torch.full_like(extra["pixels"], 7)
    buffer.extend(extra)
    del buffer
    if not torch.equal(load_dir(directory)[:200]["pixels"], original):
        raise Silent("the stored frames changed")


def _collect_in(directory: str, frames: int, seed: int) -> None:
    torch.set_num_threads(1)
    collect_play_data(
        KeyWallEnv(batch_size=(4,)), frames, directory=directory, seed=seed, trajectory_length=50
    )


@fault("data", "two collections into one directory at once", ("being written",))
def _concurrent() -> Any:
    directory = fresh("concurrent")
    context = mp.get_context("spawn")
    first = context.Process(target=_collect_in, args=(str(directory), 400_000, 0))
    first.start()
    try:
        deadline = time.monotonic() + 120
        while not (directory / "storage").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        collect_play_data(
            KeyWallEnv(batch_size=(4,)), 2000, directory=directory, seed=1, trajectory_length=50
        )
        raise Silent("a second collection ran into a directory being written")
    finally:
        first.terminate()
        first.join()


@fault("data", "directory= names an existing file", ("directory",))
def _directory_is_file() -> Any:
    path = fresh("file")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("notes")
    collect_play_data(KeyWallEnv(batch_size=(2,)), 20, directory=path, seed=0)


# ------------------------------------------------------------------ checkpoints
def _flipped_checkpoint(kind: str, fraction: float) -> Callable[[], Any]:
    def run() -> Any:
        path = checkpoint(kind)
        good = weights(load_encoder(path) if kind == "rep" else load_video_model(path))
        flip(path, fraction)
        loaded = load_encoder(path) if kind == "rep" else load_video_model(path)
        if not same(weights(loaded), good):
            raise Silent("changed weights loaded")
        return HARMLESS  # the byte changed nothing that is read

    return run


for _kind in ("rep", "wm"):
    for _fraction in (0.2, 0.35, 0.5, 0.65, 0.8, 0.9):
        FAULTS.append(
            Fault(
                "checkpoint",
                f"flipped byte at {_fraction:.0%} of a {_kind} checkpoint",
                _flipped_checkpoint(_kind, _fraction),
                ("corrupted",),
            )
        )


@fault("checkpoint", "flipped byte, then train(resume=True)", ("corrupted",))
def _flipped_resume() -> Any:
    path = checkpoint("rep")
    good = weights(load_encoder(path))
    flip(path, 0.5)
    trainer = RepresentationTrainer(rep_config(out_dir=str(path.parent.parent)))
    trainer.train(resume=True)  # the checkpoint is at the last step: nothing more is trained
    if not same(weights(trainer.encoder.eval()), good):
        raise Silent("resumed from changed weights")
    return HARMLESS


@fault("checkpoint", "NaN weights in a checkpoint (load_encoder)", ("nan",))
def _nan_rep() -> Any:
    def edit(payload: dict) -> None:
        name = next(iter(payload["state"]["encoder"]))
        payload["state"]["encoder"][name] = torch.full_like(
            payload["state"]["encoder"][name], math.nan
        )

    load_encoder(legacy_checkpoint("rep", edit))
    raise Silent("NaN weights loaded")


@fault("checkpoint", "infinite weights in a checkpoint (load_video_model)", ("inf",))
def _inf_wm() -> Any:
    def edit(payload: dict) -> None:
        payload["state"]["model"]["copy_gain"] = torch.tensor(math.inf)

    load_video_model(legacy_checkpoint("wm", edit))
    raise Silent("infinite weights loaded")


@fault("checkpoint", "missing 'encoder' entry", ("encoder", "last.pt"))
def _missing_encoder() -> Any:
    load_encoder(legacy_checkpoint("rep", lambda p: p["state"].pop("encoder")))


@fault("checkpoint", "missing 'model' entry", ("model", "last.pt"))
def _missing_model() -> Any:
    load_video_model(legacy_checkpoint("wm", lambda p: p["state"].pop("model")))


@fault("checkpoint", "missing 'state' entry", ("state", "last.pt"))
def _missing_state() -> Any:
    load_encoder(legacy_checkpoint("rep", lambda p: p.pop("state")))


@fault("checkpoint", "truncated checkpoint", ("corrupted",))
def _truncated_checkpoint() -> Any:
    path = checkpoint("rep")
    path.write_bytes(path.read_bytes()[:500])
    load_encoder(path)


@fault("checkpoint", "empty checkpoint file", ("corrupted",))
def _empty_checkpoint() -> Any:
    path = checkpoint("rep")
    path.write_bytes(b"")
    load_encoder(path)


@fault("checkpoint", "no checkpoint file", ("no checkpoint",), (FileNotFoundError,))
def _no_checkpoint() -> Any:
    load_encoder(fresh("none") / "last.pt")


def _resume_with(change: dict[str, Any], words: tuple[str, ...]) -> None:
    def run() -> Any:
        path = checkpoint("rep")
        trainer = RepresentationTrainer(rep_config(out_dir=str(path.parent.parent), **change))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trainer.train(resume=True)
        said = any(name in str(w.message) for w in caught for name in change)
        if "lr" in change and trainer.optimizer.param_groups[0]["lr"] == change["lr"] and said:
            return HARMLESS  # taken, and said so
        raise Silent(f"resumed with {change} without a word")

    FAULTS.append(Fault("checkpoint", f"resume with another {'/'.join(change)}", run, words))


_resume_with({"lr": 1e-2}, ("lr",))
_resume_with({"batch_size": 16}, ("batch_size",))
_resume_with({"seed": 3}, ("seed",))
_resume_with({"usage_weight": 1.0}, ("usage_weight",))


# ------------------------------------------------------------------ training
def _train(kind: str, **overrides: Any) -> Callable[[], Any]:
    def run() -> Any:
        cfg = rep_config(**overrides) if kind == "rep" else wm_config(**overrides)
        trainer = RepresentationTrainer(cfg) if kind == "rep" else WorldModelTrainer(cfg)
        result = trainer.train()
        model = trainer.encoder if kind == "rep" else trainer.model
        finite = all(torch.isfinite(p).all() for p in model.parameters())
        if not finite or not all(math.isfinite(v) for v in result["metrics"].values()):
            raise Silent("finished with NaN or infinite weights or loss")
        raise Silent(f"trained with {overrides}")

    return run


for _kind in ("rep", "wm"):
    for _field, _value, _words in [
        ("lr", 1e9, ("step",)),
        ("lr", math.nan, ("lr",)),
        ("lr", -1.0, ("lr",)),
        ("num_steps", 2.5, ("num_steps",)),
        ("num_envs", 0, ("num_envs",)),
        ("seed", -1, ("seed",)),
        ("batch_size", 0, ("batch_size",)),
        ("log_every", 0, ("log_every",)),
        ("checkpoint_every", 1.5, ("checkpoint_every",)),
        ("device", "gpu0", ("device",)),
        ("progress", "no", ("progress",)),
        ("env", "maze", ("env",)),
    ]:
        FAULTS.append(
            Fault(
                "training",
                f"{_kind} {_field}={_value!r}",
                _train(_kind, **{_field: _value}),
                _words,
            )
        )

for _field, _value in [
    ("grad_clip", 0.0),
    ("grad_clip", -1.0),
    ("grad_clip", math.nan),
    ("kl_weight", math.nan),
    ("deterministic_fraction", 1.5),
    ("open_loop_ramp", 2.0),
    ("horizon", 0),
    ("lr_final", -1.0),
    ("eval_sequences", 0),
]:
    FAULTS.append(
        Fault("training", f"wm {_field}={_value!r}", _train("wm", **{_field: _value}), (_field,))
    )

for _field, _value in [
    ("max_offset", 4),
    ("batch_size", 1),
    ("gumbel_temperature", 0.0),
    ("ce_temperature", -1.0),
    ("usage_weight", math.nan),
    ("alpha", 0.5),
    ("encoder", {"code_sizes": (1,)}),
    ("num_objects", 0),
]:
    FAULTS.append(
        Fault("training", f"rep {_field}={_value!r}", _train("rep", **{_field: _value}), (_field,))
    )

FAULTS.append(
    Fault(
        "training",
        "rep num_objects=3 with env='key-wall' (ignored)",
        _train("rep", env="key-wall", num_objects=3),
        ("num_objects",),
    )
)


@fault(
    "training",
    "RepresentationTrainer(buffer=key-wall data) under a rearrangement config",
    ("environment",),
)
def _foreign_buffer() -> Any:
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 256, seed=0)
    RepresentationTrainer(rep_config(), buffer=buffer).train()
    raise Silent("trained on another environment's data")


@fault(
    "training",
    "RepresentationTrainer(buffer=2-object data) under a 1-object config",
    ("environment",),
)
def _two_object_buffer() -> Any:
    buffer = collect_play_data(ObjectRearrangementEnv(2, batch_size=(4,)), 256, seed=0)
    RepresentationTrainer(rep_config(), buffer=buffer).train()
    raise Silent("trained on another environment's data")


@fault(
    "training",
    "WorldModelTrainer(buffer=key-wall data) under a rearrangement config",
    ("environment",),
)
def _foreign_wm_buffer() -> Any:
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 256, seed=0, trajectory_length=8)
    WorldModelTrainer(wm_config(), buffer=buffer).train()
    raise Silent("trained on another environment's data")


# ------------------------------------------------------------------ envs
def _env(factory: Callable[[], Any], check: Callable[[Any], bool] | None = None) -> Callable:
    def run() -> Any:
        out = factory()
        if check is not None:
            if not check(out):
                raise Silent(f"wrong result {out!r}"[:200])
            return out
        raise Silent("accepted")

    return run


for _name, _factory, _words in [
    ("num_objects=2.7", lambda: ObjectRearrangementEnv(num_objects=2.7).reset(), ("num_objects",)),
    ("num_objects='2'", lambda: ObjectRearrangementEnv(num_objects="2").reset(), ("num_objects",)),
    ("batch_size=(-1,)", lambda: ObjectRearrangementEnv(batch_size=(-1,)).reset(), ("batch_size",)),
    (
        "batch_size=(0,)",
        lambda: ObjectRearrangementEnv(batch_size=(0,)).rollout(3),
        ("batch_size",),
    ),
    ("batch_size=(2.5,)", lambda: KeyWallEnv(batch_size=(2.5,)).reset(), ("batch_size",)),
    ("seed=-1", lambda: ObjectRearrangementEnv(seed=-1).reset(), ("seed",)),
    ("seed=1.5", lambda: KeyWallEnv(seed=1.5).reset(), ("seed",)),
    ("set_seed(-1)", lambda: KeyWallEnv().set_seed(-1), ("seed",)),
    ("max_steps=0", lambda: KeyWallEnv(max_steps=0).reset(), ("max_steps",)),
    ("max_steps=2.5", lambda: KeyWallEnv(max_steps=2.5).rollout(5), ("max_steps",)),
    (
        "block_shapes=(2.5, 4)",
        lambda: ObjectRearrangementEnv(block_shapes=(2.5, 4)).reset(),
        ("block_shapes",),
    ),
    (
        "colours as floats 0..1",
        lambda: ObjectRearrangementEnv(1, colours=[[0.5, 0.2, 0.1]]).reset(),
        ("colours",),
    ),
]:
    FAULTS.append(Fault("envs", _name, _env(_factory), _words))

FAULTS.append(
    Fault(
        "envs",
        "batch_size=4 (an int)",
        _env(
            lambda: ObjectRearrangementEnv(batch_size=4).reset(), lambda td: td.batch_size == (4,)
        ),
        ("batch_size",),
        may_handle=True,
    )
)


def _step_with(state_fn: Callable[[Any], torch.Tensor], env_fn: Callable[[], Any]) -> Callable:
    def run() -> Any:
        env = env_fn()
        td = env.reset()
        td["state"] = state_fn(td)
        td["action"] = torch.zeros(*env.batch_size, 1, dtype=torch.int64)
        env.step(td)
        raise Silent("an invalid state was stepped and drawn")

    return run


for _name, _state, _env_fn in [
    (
        "overlapping blocks written before step()",
        lambda td: torch.tensor([[[0, 0], [0, 0]]] * 2),
        lambda: ObjectRearrangementEnv(2, batch_size=(2,), seed=0),
    ),
    (
        "block off the grid written before step()",
        lambda td: torch.tensor([[[15, 14]]] * 2),
        lambda: ObjectRearrangementEnv(1, batch_size=(2,), seed=0),
    ),
    (
        "agent in a wall written before step()",
        lambda td: torch.tensor([[0, 8, 0]] * 2),
        lambda: KeyWallEnv(batch_size=(2,), seed=0),
    ),
    (
        "has-key flag 2 written before step()",
        lambda td: torch.tensor([[3, 3, 2]] * 2),
        lambda: KeyWallEnv(batch_size=(2,), seed=0),
    ),
    (
        "state of another shape written before step()",
        lambda td: torch.zeros(2, 3, 2, dtype=torch.int64),
        lambda: ObjectRearrangementEnv(2, batch_size=(2,), seed=0),
    ),
    (
        "float state written before step()",
        lambda td: td["state"].float(),
        lambda: KeyWallEnv(batch_size=(2,), seed=0),
    ),
]:
    FAULTS.append(Fault("envs", _name, _step_with(_state, _env_fn), ("state",)))


@fault("envs", "a 3-row tensordict stepped in a 4-env batch", ("batch_size",))
def _rows_mismatch() -> Any:
    env = ObjectRearrangementEnv(2, batch_size=(4,), seed=0)
    env.step(TensorDict(action=torch.zeros(3, 1, dtype=torch.int64), batch_size=[3]))


@fault("envs", "step() on a tensordict without 'state'", ("state",))
def _no_state() -> Any:
    env = KeyWallEnv(batch_size=(2,), seed=0)
    env.step(TensorDict(action=torch.zeros(2, 1, dtype=torch.int64), batch_size=[2]))


@fault("envs", "terminate_on_success='no'", ("terminate_on_success",))
def _bool_string() -> Any:
    env = KeyWallEnv(terminate_on_success="no", seed=0)
    if env.terminate_on_success:
        raise Silent("'no' read as True")


@fault("envs", "gymnasium reset(seed=-1)", ("seed",))
def _gym_seed() -> Any:
    import gymnasium

    gymnasium.make("dorp_rl/KeyWall-v0").reset(seed=-1)


# ------------------------------------------------------------------ planning
def _rs(planning_env: Any, **kwargs: Any) -> VisualForesightPolicy:
    return VisualForesightPolicy(
        planning_env, "rs", planning_horizon=3, num_candidates=8, seed=0, **kwargs
    )


@fault("planning", "2-object planning env with a 1-object acting env", ("state",))
def _planning_mismatch() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    env.rollout(2, _rs(GroundTruthModelEnv(ObjectRearrangementEnv(2, seed=0))))
    raise Silent("planned in another world")


@fault("planning", "key-wall planning env with a rearrangement acting env", ("state",))
def _planning_mismatch_keys() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    env.rollout(2, _rs(GroundTruthModelEnv(KeyWallEnv(seed=0))))
    raise Silent("planned in another world")


@fault("planning", "VideoModelEnv(model, 2) on a 4-action env", ("num_actions",))
def _world_model_actions() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours.cpu()])
    model = VideoPredictionModel(env.num_actions, palette, VideoModelConfig.small()).eval()
    env.rollout(2, _rs(VideoModelEnv(model, 2)))
    raise Silent("planned with actions 0 and 1 only")


@fault("planning", "evaluate_policy(max_steps=0)", ("max_steps",))
def _max_steps_zero() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    result = evaluate_policy(env, _rs(GroundTruthModelEnv(env)), make_task_set(env, 1), max_steps=0)
    raise Silent(f"ran {result['max_steps']} steps")


@fault("planning", "evaluate_policy(report_keys=[a key the policy never writes])", ("nope",))
def _report_key() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    tasks = make_task_set(env, 1)
    evaluate_policy(env, _rs(GroundTruthModelEnv(env)), tasks, max_steps=2, report_keys=["nope"])


@fault("planning", "evaluate_policy(tasks_per_rollout=0)", ("tasks_per_rollout",))
def _tasks_zero() -> Any:
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    evaluate_policy(env, _rs(GroundTruthModelEnv(env)), make_task_set(env, 1), tasks_per_rollout=0)


def _code_cost(target: int) -> Callable[[], Any]:
    def run() -> Any:
        encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        rollout = TensorDict(
            {
                "pixels": frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16),
                "subgoal_code": torch.full((2, 1, 1, 2), target).expand(2, 5, 4, 2),
                ("next", "pixels"): frames,
            },
            batch_size=(2, 5, 4),
        )
        CodeMatchCost(encoder)(rollout)
        raise Silent("scored an impossible target")

    return run


FAULTS.append(
    Fault("planning", "CodeMatchCost target 9 of 8 codes", _code_cost(9), ("subgoal_code",))
)
FAULTS.append(Fault("planning", "CodeMatchCost target -1", _code_cost(-1), ("subgoal_code",)))


def _planner(**kwargs: Any) -> Callable[[], Any]:
    def run() -> Any:
        env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
        options = {"planning_horizon": 3, "num_candidates": 8, "seed": 0} | kwargs
        cls = CategoricalCEMPlanner if "top_k" in kwargs else RandomShootingPlanner
        env.rollout(2, cls(GroundTruthModelEnv(env), PixelDistanceCost(), **options))
        raise Silent(f"planned with {kwargs}")

    return run


for _kwargs, _words in [
    ({"num_candidates": 2.5}, ("num_candidates",)),
    ({"planning_horizon": 0}, ("planning_horizon",)),
    ({"seed": -1}, ("seed",)),
    ({"top_k": 50}, ("top_k",)),
]:
    FAULTS.append(Fault("planning", f"planner {_kwargs}", _planner(**_kwargs), _words))

FAULTS.append(
    Fault(
        "planning",
        "make_task_set(num_tasks=0)",
        lambda: make_task_set(KeyWallEnv(), 0),
        ("num_tasks",),
    )
)
FAULTS.append(
    Fault(
        "planning",
        "make_task_set(seed=-1)",
        _env(lambda: make_task_set(KeyWallEnv(), 2, seed=-1)),
        ("seed",),
    )
)


# ------------------------------------------------------------------ encoders
def _encoder() -> DiscreteCodeEncoder:
    torch.manual_seed(0)
    return DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(16,))).eval()


def _frames() -> torch.Tensor:
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    return env.render_state(env.sample_states((64,)))


@fault("encoders", "float pixels in 0..255 (forgotten / 255)", ("[0, 1]",))
def _float_255() -> Any:
    encoder, frames = _encoder(), _frames()
    if torch.equal(encoder(frames.float())[0], encoder(frames)[0]):
        return HARMLESS
    raise Silent("other codes than the uint8 frames")


@fault("encoders", "NaN float pixels", ("pixels",))
def _nan_pixels() -> Any:
    _encoder()(torch.full((2, 3, 16, 16), math.nan))
    raise Silent("encoded NaN frames")


@fault("encoders", "numpy uint8 frames to encode()", ("numpy",), may_handle=True)
def _numpy_encode() -> Any:
    encoder, frames = _encoder(), _frames()
    if not torch.equal(encoder.encode(frames.numpy()), encoder.encode(frames)):
        raise Silent("other codes than the tensor frames")


@fault("encoders", "numpy uint8 frames to forward()", ("torch.Tensor",), may_handle=True)
def _numpy_forward() -> Any:
    encoder, frames = _encoder(), _frames()
    if not torch.equal(encoder(frames.numpy())[0], encoder(frames)[0]):
        raise Silent("other codes than the tensor frames")


@fault("encoders", "int32 frames", ("uint8",))
def _int_frames() -> Any:
    _encoder()(_frames().to(torch.int32))


@fault("encoders", "channel-last frames", ("3, 16, 16",))
def _channel_last() -> Any:
    _encoder()(_frames().movedim(-3, -1))


@fault("encoders", "video model: float frames in [0, 1]", None)
def _video_float() -> Any:
    env = ObjectRearrangementEnv(1, seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours.cpu()])
    torch.manual_seed(0)
    model = VideoPredictionModel(4, palette, VideoModelConfig.small()).eval()
    actions = torch.zeros(64, 1, dtype=torch.int64)
    frames = _frames()
    if not torch.equal(
        model.predict(frames.float() / 255, actions), model.predict(frames, actions)
    ):
        raise Silent("other predictions for float frames than for the uint8 frames")


@fault("encoders", "video model: action 4 of 4", ("action",))
def _video_action() -> Any:
    env = ObjectRearrangementEnv(1, seed=0)
    palette = torch.cat([torch.zeros(1, 3, dtype=torch.uint8), env.colours.cpu()])
    model = VideoPredictionModel(4, palette, VideoModelConfig.small())
    model.predict(_frames(), torch.full((64, 1), 4))


# ------------------------------------------------------------------ goals and policies
def _tiny_dorp(env: Any) -> Any:
    """A DORP policy of an untrained 1-one-hot encoder over ``env``'s play data."""
    from dorp_rl.planners import CodeGraph
    from dorp_rl.policies import make_dorp_policy

    encoder = _encoder()
    buffer = collect_play_data(type(env)(**_same_world(env), batch_size=(16,)), 256, seed=0)
    graph = CodeGraph.from_play_data(buffer, encoder)
    return make_dorp_policy(env, encoder, graph, num_candidates=8, planning_horizon=3, seed=0)


def _same_world(env: Any) -> dict[str, Any]:
    return {"num_objects": env.num_objects} if hasattr(env, "num_objects") else {}


_ACTORS: dict[str, Callable[[Any], Any]] = {
    "DORP policy": _tiny_dorp,
    "VF-RS": lambda env: _rs(GroundTruthModelEnv(env)),
    "random shooting": lambda env: RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=3, num_candidates=8, seed=0
    ),
    "CEM": lambda env: CategoricalCEMPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=3, num_candidates=8,
        top_k=4, seed=0,
    ),
}  # fmt: skip

_BAD_GOALS: dict[str, Callable[[Any], torch.Tensor]] = {
    "a key-wall goal image": lambda td: KeyWallEnv(batch_size=(2,), seed=0).reset()["pixels"],
    "a 2-object goal image": lambda td: ObjectRearrangementEnv(2, batch_size=(2,), seed=0).reset()[
        "pixels"
    ],
    "an all-black goal image": lambda td: torch.zeros_like(td["goal_pixels"]),
    "an all-NaN goal image": lambda td: torch.full(td["goal_pixels"].shape, math.nan),
    "a float goal image in 0..255": lambda td: td["goal_pixels"].float(),
}


def _bad_goal(actor: str, goal: str) -> Callable[[], Any]:
    def run() -> Any:
        env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
        policy = _ACTORS[actor](env)
        td = env.reset()
        td["goal_pixels"] = _BAD_GOALS[goal](td)
        policy(td)
        raise Silent(f"planned towards {goal}")

    return run


for _actor in _ACTORS:
    for _goal in _BAD_GOALS:
        FAULTS.append(Fault("goals", f"{_actor}: {_goal}", _bad_goal(_actor, _goal), ("goal",)))


def _dorp_with(**kwargs: Any) -> Callable[[], Any]:
    def run() -> Any:
        from dorp_rl.planners import CodeGraph
        from dorp_rl.policies import make_dorp_policy

        env = ObjectRearrangementEnv(1, batch_size=(2,), seed=0)
        encoder = _encoder()
        buffer = collect_play_data(ObjectRearrangementEnv(1, batch_size=(16,)), 256, seed=0)
        graph = CodeGraph.from_play_data(buffer, encoder)
        options = {"num_candidates": 8, "planning_horizon": 3, "seed": 0} | kwargs
        make_dorp_policy(env, encoder, graph, **options)(env.reset())
        raise Silent(f"planned with {kwargs}")

    return run


for _kwargs, _words in [
    ({"goal_code_weight": math.nan}, ("goal_code_weight",)),
    ({"waypoint_step_penalty": math.inf}, ("waypoint_step_penalty",)),
    ({"action_persistence": 1.5}, ("action_persistence",)),
    ({"waypoint_goal_weight": -1.0}, ("waypoint_goal_weight",)),
    ({"bogus_option": 3}, ("bogus_option",)),
]:
    FAULTS.append(
        Fault("goals", f"make_dorp_policy({_kwargs})", _dorp_with(**_kwargs), _words,
              errors=(ValueError, TypeError))
    )  # fmt: skip


@fault("goals", "NegativeRewardCost: rewards after done", None)
def _reward_after_done() -> Any:
    from dorp_rl.planners import NegativeRewardCost

    done = torch.tensor([False, True, False, False]).reshape(1, 1, 4, 1)
    rollout = TensorDict(
        {("next", "reward"): torch.ones(1, 1, 4, 1), ("next", "done"): done},
        batch_size=(1, 1, 4),
    )
    cost = NegativeRewardCost()(rollout)["cost"][0, 0]
    if cost[2:].abs().sum() != 0:
        raise Silent(f"per-step costs {cost.tolist()} count the rewards after done")


@fault("goals", "CodeMatchCost(onehots=(5,)) on a 1-one-hot encoder", ("onehots",))
def _onehots_out_of_range() -> Any:
    CodeMatchCost(_encoder(), onehots=(5,))


# ------------------------------------------------------------------ graphs and tasks
def _graph(objects: int = 1, encoder: Any = None) -> Any:
    from dorp_rl.planners import CodeGraph

    buffer = collect_play_data(ObjectRearrangementEnv(objects, batch_size=(16,)), 256, seed=0)
    return CodeGraph.from_play_data(buffer, encoder or _encoder())


@fault("graphs", "a 1-object encoder over 2-object play data", ("env",))
def _foreign_graph() -> Any:
    trainer = RepresentationTrainer(rep_config())
    trainer.train()
    _graph(2, trainer.encoder)
    raise Silent("built a graph of codes for another env")


for _name, _args, _words in [
    ("shortest_path(0, -1, 0)", (0, -1, 0), ("start",)),
    ("shortest_path(0, 0.5, 0)", (0, 0.5, 0), ("start",)),
    ("shortest_path(0, 0, 99)", (0, 0, 99), ("goal",)),
    ("shortest_path(7, 0, 0)", (7, 0, 0), ("group",)),
]:
    FAULTS.append(
        Fault("graphs", _name, lambda a=_args: _graph().shortest_path(*a) and None, _words)
    )


@fault("graphs", "from_play_data(chunk_size=0)", ("chunk_size",))
def _chunk_zero() -> Any:
    from dorp_rl.planners import CodeGraph

    buffer = collect_play_data(ObjectRearrangementEnv(1, batch_size=(16,)), 256, seed=0)
    CodeGraph.from_play_data(buffer, _encoder(), chunk_size=0)


@fault("graphs", "a graph file with an unknown config field", ("bogus_field",))
def _graph_unknown_field() -> Any:
    from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
    from dorp_rl.planners import CodeGraph

    path = _graph().save(fresh("graph") / "graph.pt")
    stored = load_checkpoint(path, kind="code_graph")
    save_checkpoint(
        path, kind="code_graph", config={**stored["config"], "bogus_field": 1},
        env_config=stored.get("env_config") or {}, state=stored["state"], step=0,
    )  # fmt: skip
    CodeGraph.load(path)
    raise Silent("loaded a graph with an unknown config field")


def _tasks(num: int = 2) -> tuple[Any, Any]:
    env = ObjectRearrangementEnv(1, batch_size=(), batch_locked=False, seed=0)
    return env, make_task_set(env, num)


def _lower_bound(state: Callable[[Any], Any], goal: Callable[[Any], Any]) -> Callable[[], Any]:
    def run() -> Any:
        env, tasks = _tasks(3)
        env.lower_bound_steps(state(tasks), goal(tasks))
        raise Silent("returned a bound")

    return run


FAULTS.append(
    Fault("tasks", "lower_bound_steps: start and goal of other shapes",
          _lower_bound(lambda t: t["state"][:1], lambda t: t["goal_state"]), ("shape",))
)  # fmt: skip
FAULTS.append(
    Fault("tasks", "lower_bound_steps: a goal off the grid",
          _lower_bound(lambda t: t["state"], lambda t: t["goal_state"] + 40), ("goal",))
)  # fmt: skip


def _evaluate_on(edit: Callable[[Any], Any]) -> Callable[[], Any]:
    def run() -> Any:
        env, tasks = _tasks()
        result = evaluate_policy(env, _rs(GroundTruthModelEnv(env)), edit(tasks), max_steps=2)
        raise Silent(f"success {result.get('success_rate')}")

    return run


def _lower_bounds(values: list[float]) -> Callable[[Any], Any]:
    def edit(tasks: Any) -> Any:
        tasks = tasks.clone()
        tasks["lower_bound"] = torch.tensor(values)
        return tasks

    return edit


for _name, _edit, _words in [
    ("evaluate_policy on an empty task set", lambda t: t[:0], ("task",)),
    ("evaluate_policy: a negative lower bound", _lower_bounds([-1, 3]), ("lower_bound",)),
    ("evaluate_policy: a NaN lower bound", _lower_bounds([math.nan, 3.0]), ("lower_bound",)),
]:
    FAULTS.append(Fault("tasks", _name, _evaluate_on(_edit), _words))


@fault("tasks", "a task whose start is its goal", None)
def _start_is_goal() -> Any:
    env, tasks = _tasks(1)
    tasks = tasks.clone()
    tasks["goal_state"] = tasks["state"].clone()
    tasks["lower_bound"] = torch.zeros_like(tasks["lower_bound"])
    result = evaluate_policy(env, _rs(GroundTruthModelEnv(env)), tasks, max_steps=3)
    if result["success_rate"] != 1.0:
        raise Silent(f"counted as failed (success {result['success_rate']})")


@fault("tasks", "make_task_set('env', 4)", ("env",))
def _task_set_of_a_string() -> Any:
    make_task_set("env", 4)


@fault("tasks", "evaluate_policy(env, 'random', tasks)", ("policy",))
def _policy_string() -> Any:
    env, tasks = _tasks()
    evaluate_policy(env, "random", tasks, max_steps=2)


@fault("tasks", "FuturePairSampler(1, 4) over one-step trajectories", ("offset",))
def _unreachable_offset() -> Any:
    from dorp_rl.data import FuturePairSampler, future_pairs

    buffer = collect_play_data(
        ObjectRearrangementEnv(1, batch_size=(4,)), 64, sampler=FuturePairSampler(1, 4),
        batch_size=64, seed=0,
    )  # fmt: skip
    _, _, offset = future_pairs(buffer.sample())
    raise Silent(f"sampled offsets up to {int(offset.max())} of 4, without a word")


# ------------------------------------------------------------------ arguments
for _name, _run, _words in [
    ("env device='foo'", lambda: ObjectRearrangementEnv(1, device="foo").reset(), ("device",)),
    ("env batch_size='8'", lambda: ObjectRearrangementEnv(1, batch_size="8").reset(),
     ("batch_size",)),
    ("env.rollout(0)", lambda: ObjectRearrangementEnv(1, seed=0).rollout(0), ("max_steps",)),
    ("world-model config eval_frames=4", lambda: WorldModelTrainer(wm_config(eval_frames=4)),
     ("eval_frames",)),
]:  # fmt: skip
    FAULTS.append(Fault("arguments", _name, _run, _words))

if not torch.cuda.is_available():
    for _name, _run in [
        (
            "env device='cuda' without CUDA",
            lambda: ObjectRearrangementEnv(1, device="cuda").reset(),
        ),
        ("config device='cuda' without CUDA", lambda: rep_config(device="cuda")),
    ]:
        FAULTS.append(Fault("arguments", _name, _run, ("cuda",)))


def _float_frames(dtype: torch.dtype) -> Callable[[], Any]:
    def run() -> Any:
        encoder, frames = _encoder(), _frames()
        if not torch.equal(encoder.encode(frames.to(dtype) / 255), encoder.encode(frames)):
            raise Silent(f"other codes for {dtype} frames than the uint8 frames")

    return run


for _dtype in (torch.float64, torch.float16):
    FAULTS.append(
        Fault("arguments", f"{_dtype} frames in [0, 1] to encode()", _float_frames(_dtype), None)
    )  # fmt: skip


# ------------------------------------------------------------------ command line
#: a tiny collection for the command's faults (seconds, not minutes)
_TINY = ["--setting", "1obj", "--threads", "1", "--codes.num-frames", "2000"]


def _dorp(*argv: str, wait: bool = True, **kwargs: Any) -> Any:
    """Runs ``python -m dorp_rl *argv`` (a new process, as a user would)."""
    command = [sys.executable, "-m", "dorp_rl", *argv]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs
    )
    if not wait:
        return process
    out, err = process.communicate(timeout=600)
    return process.returncode, out, err


def _refused(code: int, err: str) -> None:
    """A usage message (exit 2, no traceback) is the command's clear error."""
    if code == 2 and "Traceback" not in err:
        raise ValueError(err.strip().splitlines()[-1])
    if "Traceback" in err:
        raise RuntimeError(err.strip().splitlines()[-1])


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def _cli_name(name: str) -> Callable[[], Any]:
    def run() -> Any:
        base = fresh("cli-name")
        runs = base / "nest" / "runs"
        runs.mkdir(parents=True)
        code, _, err = _dorp("collect", *_TINY, "--root", str(runs), "--name", name)
        outside = [p for p in base.rglob("*") if p.is_file() and runs not in p.parents]
        _refused(code, err)
        if outside or any(runs.iterdir()):
            raise Silent(f"wrote {len(outside)} files outside the root, or into it directly")
        raise Silent(f"--name {name!r} taken (exit {code})")

    return run


for _name in ["../../escape", "/tmp/dorp-absolute-escape", "", ".", "a/../.."]:
    FAULTS.append(Fault("command line", f"--name {_name!r}", _cli_name(_name), ("--name",)))


@fault("command line", "two commands on one run folder at once", ("in use", "process"))
def _cli_two_commands() -> Any:
    runs = fresh("cli-two")
    first = _dorp(
        "collect", *_TINY[:4], "--codes.num-frames", "200000", "--root", str(runs),
        "--name", "r", wait=False,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not (runs / "r" / "play").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        code, _, err = _dorp("collect", *_TINY, "--root", str(runs), "--name", "r")
        first_code = first.wait(timeout=600)
        if first_code != 0:
            raise Silent(f"the first command ended with exit {first_code}")
        load_play_data(runs / "r" / "play")  # the first command's data are whole
        _refused(code, err)
        raise Silent("a second command ran on a busy run folder")
    finally:
        first.kill()
        first.wait()


def _cli_damaged_run(damage: Callable[[Path], None]) -> Callable[[], Any]:
    def run() -> Any:
        runs = fresh("cli-damaged")
        code, _, err = _dorp("collect", *_TINY, "--root", str(runs), "--name", "r")
        if code != 0:
            raise RuntimeError(f"the first collect failed: {err[-300:]}")
        damage(runs / "r")
        before = _snapshot(runs / "r")
        code, _, err = _dorp("build-graph", *_TINY, "--root", str(runs), "--name", "r")
        changed = _snapshot(runs / "r") != before
        _refused(code, err)
        raise Silent(f"exit {code}, run folder changed: {changed}")

    return run


def _write(name: str, text: str) -> Callable[[Path], None]:
    return lambda folder: (folder / name).write_text(text)


def _swap_play(folder: Path) -> None:
    shutil.rmtree(folder / "play")
    shutil.copytree(play_dir(), folder / "play")


for _name, _damage, _words in [
    ("stages.json corrupt", _write("stages.json", "{not json"), ("stages.json",)),
    ("stages.json empty", _write("stages.json", ""), ("stages.json",)),
    ("stages.json is []", _write("stages.json", "[]"), ("stages.json",)),
    ("stages.json without a config", _write("stages.json", '{"play": {}}'), ("stages.json",)),
    ("play/ swapped for other data", _swap_play, ("play",)),
]:
    FAULTS.append(Fault("command line", _name, _cli_damaged_run(_damage), _words))


@fault("command line", "--root is a file", ("--root",))
def _cli_root_file() -> Any:
    path = fresh("cli-root-file")
    path.write_text("notes")
    code, _, err = _dorp("collect", *_TINY, "--root", str(path), "--name", "r")
    _refused(code, err)
    raise Silent(f"exit {code}")


def _cli_low_level(make: Callable[[Path], Path]) -> Callable[[], Any]:
    def run() -> Any:
        runs = fresh("cli-low-level")
        runs.mkdir(parents=True)
        target = make(runs)
        code, _, err = _dorp(
            "evaluate", "--setting", "keywall", *_TINY[2:], "--root", str(runs), "--name", "r",
            "--tasks", "1", "--methods", "vf-rs", "--candidates", "8", "--planning-horizon", "2",
            "--max-steps", "2", "--low-level", str(target),
        )  # fmt: skip
        _refused(code, err)
        raise Silent(f"exit {code}")

    return run


def _text_file(folder: Path) -> Path:
    (folder / "notes.pt").write_text("not a checkpoint")
    return folder / "notes.pt"


for _name, _make in [
    ("--low-level: a text file", _text_file),
    ("--low-level: an encoder checkpoint", lambda folder: checkpoint("rep")),
    ("--low-level: a 1-object world model for key-wall", lambda folder: checkpoint("wm")),
]:
    FAULTS.append(Fault("command line", _name, _cli_low_level(_make), ("--low-level",)))


# ------------------------------------------------------------------ runner
def classify(item: Fault) -> tuple[str, str]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with contextlib.redirect_stderr(io.StringIO()):
                result = item.run()
        except Silent as err:
            return "silent", str(err)
        except Exception as err:
            message = f"{type(err).__name__}: {err}"
            named = item.words is not None and all(
                w.lower() in str(err).lower() for w in item.words
            )
            if isinstance(err, item.errors) and named:
                return "clear", message
            depth = len(traceback.extract_tb(err.__traceback__))
            return "unclear", f"{message} (traceback depth {depth})"
    if result == HARMLESS or item.may_handle or item.words is None:
        return "handled", ""
    return "silent", "no error"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_threads_argument(parser)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--show", nargs="*", default=["silent", "unclear"])
    parser.add_argument("--only", default=None, help="run the categories containing this")
    args = parse_with_threads(parser)
    rows = []
    start = time.perf_counter()
    for item in FAULTS:
        if args.only and args.only not in item.category:
            continue
        outcome, detail = classify(item)
        rows.append(
            {"category": item.category, "fault": item.name, "outcome": outcome, "detail": detail}
        )
        if outcome in args.show:
            print(f"[{outcome}] {item.category}: {item.name}: {detail[:240]}")
    shutil.rmtree(root(), ignore_errors=True)
    counts = Counter((r["category"], r["outcome"]) for r in rows)
    outcomes = ("clear", "handled", "unclear", "silent")
    print(f"\n{'category':<12}" + "".join(f"{o:>9}" for o in outcomes) + f"{'total':>8}")
    for category in dict.fromkeys(r["category"] for r in rows):
        cells = [counts[(category, o)] for o in outcomes]
        print(f"{category:<12}" + "".join(f"{c:>9}" for c in cells) + f"{sum(cells):>8}")
    totals = Counter(r["outcome"] for r in rows)
    print(f"{'all':<12}" + "".join(f"{totals[o]:>9}" for o in outcomes) + f"{len(rows):>8}")
    print(f"({time.perf_counter() - start:.0f} s)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
