"""Checkpoints: checksummed payloads, finite weights, complete entries, honest resumes.

Damaged files are produced byte by byte; every load either refuses with an
``IntegrityError`` (a ``ValueError``) naming the file or returns exactly what was
saved, never something else. Refusals leave the previous good checkpoint loadable.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path
from unittest import mock

import pytest
import torch

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.integrity import IntegrityError
from dorp_rl.trainers import (
    RepresentationTrainer,
    WorldModelTrainer,
    load_encoder,
    load_video_model,
)
from dorp_rl.trainers.base import NoCheckpointWarning

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def state_of(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in module.state_dict().items()}


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def logged(out_dir: str | Path, name: str = "loss_cpc") -> list[tuple[int, str]]:
    """The (step, value) rows of one scalar in a run's CSV logs, in the order written."""
    path = Path(out_dir) / "logs" / "scalars" / f"{name}.csv"
    rows = [line.split(",") for line in path.read_text().splitlines()]
    return [(int(step), value) for step, value in rows]


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_configs) -> dict:
    """One tiny representation and one tiny world-model checkpoint (copy before damaging)."""
    root = tmp_path_factory.mktemp("checkpoints")
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    rep = RepresentationTrainer(tiny_configs.representation(root / "rep", num_steps=4))
    wm = WorldModelTrainer(tiny_configs.world_model(root / "wm", num_steps=4))
    rep.train()
    wm.train()
    torch.set_num_threads(previous)
    return {
        "rep": rep.checkpoint_path,
        "wm": wm.checkpoint_path,
        "rep_weights": state_of(load_encoder(rep.checkpoint_path)),
        "wm_weights": state_of(load_video_model(wm.checkpoint_path)),
    }


def copy_of(trained, kind: str, tmp_path) -> object:
    target = tmp_path / kind / "checkpoints" / "last.pt"
    target.parent.mkdir(parents=True)
    shutil.copy(trained[kind], target)
    return target


# ---------------------------------------------------------------- the format
def test_the_file_stores_a_checksum_of_its_payload(trained):
    outer = torch.load(trained["rep"], weights_only=True)
    payload = outer["payload"].numpy().tobytes()
    assert outer["format"] == 2 and outer["kind"] == "representation"
    assert outer["sha256"] == hashlib.sha256(payload).hexdigest()


def test_save_and_load_round_trip(tmp_path):
    state = {"model": {"w": torch.randn(3, 4), "step": torch.tensor(7)}}
    path = save_checkpoint(
        tmp_path / "c.pt", kind="k", config={"lr": 0.1}, env_config={}, state=state, step=3
    )
    payload = load_checkpoint(path, kind="k", state_keys=("model",))
    assert payload["step"] == 3 and payload["config"] == {"lr": 0.1}
    assert same(payload["state"]["model"], state["model"])


# ---------------------------------------------------------------- flipped bytes
@pytest.mark.parametrize(
    ("kind", "loader"), [("rep", load_encoder), ("wm", load_video_model)], ids=["encoder", "video"]
)
def test_no_flipped_byte_loads_changed_weights(trained, tmp_path, kind, loader):
    path = copy_of(trained, kind, tmp_path)
    good = path.read_bytes()
    refused = 0
    positions = range(0, len(good), max(1, len(good) // 97))  # ~100 spread positions
    for position in positions:
        damaged = bytearray(good)
        damaged[position] ^= 0xFF
        path.write_bytes(bytes(damaged))
        try:
            loaded = loader(path)
        except ValueError as err:
            assert str(path) in str(err)
            refused += 1
        else:  # a byte no reader looks at (zip padding, a CRC torch does not check)
            assert same(state_of(loaded), trained[f"{kind}_weights"]), f"byte {position}"
    assert refused >= 0.8 * len(positions)
    path.write_bytes(good)
    assert same(state_of(loader(path)), trained[f"{kind}_weights"])


@pytest.mark.parametrize("keep", [0, 10, 100, 1000, -200, -1])
def test_a_truncated_checkpoint_is_refused(trained, tmp_path, keep):
    path = copy_of(trained, "rep", tmp_path)
    path.write_bytes(path.read_bytes()[:keep])
    with pytest.raises(IntegrityError, match="corrupted"):
        load_encoder(path)


def test_resume_refuses_a_damaged_checkpoint_and_keeps_it(trained, tmp_path, tiny_configs):
    path = copy_of(trained, "rep", tmp_path)
    damaged = bytearray(path.read_bytes())
    damaged[len(damaged) // 2] ^= 0x10
    path.write_bytes(bytes(damaged))
    cfg = tiny_configs.representation(path.parent.parent, num_steps=4)
    with pytest.raises(IntegrityError, match="checksum"):
        RepresentationTrainer(cfg).train(resume=True)
    assert path.read_bytes() == bytes(damaged)  # not overwritten by a fresh run


# ---------------------------------------------------------------- non-finite weights
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_weights_are_never_written(tmp_path, value):
    path = save_checkpoint(
        tmp_path / "c.pt", kind="k", config={}, env_config={}, state={"w": torch.ones(2)}, step=1
    )
    good = path.read_bytes()
    bad = {"model": {"layer.weight": torch.tensor([1.0, value])}}
    with pytest.raises(IntegrityError, match="model.layer.weight"):
        save_checkpoint(path, kind="k", config={}, env_config={}, state=bad, step=2)
    assert path.read_bytes() == good
    assert load_checkpoint(path)["step"] == 1


def rewrite_as_format_1(path, edit) -> None:
    """An older (pre-checksum) checkpoint: the payload itself, after ``edit``."""
    payload = load_checkpoint(path)
    payload["format"] = 1
    edit(payload)
    torch.save(payload, path)


@pytest.mark.parametrize(
    ("kind", "loader", "entry"),
    [("rep", load_encoder, "encoder"), ("wm", load_video_model, "model")],
    ids=["encoder", "video"],
)
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_weights_are_refused_on_load(trained, tmp_path, kind, loader, entry, value):
    path = copy_of(trained, kind, tmp_path)

    def poison(payload):
        name = next(k for k, v in payload["state"][entry].items() if v.is_floating_point())
        payload["state"][entry][name] = torch.full_like(payload["state"][entry][name], value)

    rewrite_as_format_1(path, poison)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(IntegrityError, match=f"NaN or infinite values in {entry}\\."):
            loader(path)
    assert any("without a checksum" in str(w.message) for w in caught)


# ---------------------------------------------------------------- missing entries
@pytest.mark.parametrize(
    ("kind", "loader", "edit", "missing"),
    [
        ("rep", load_encoder, lambda p: p["state"].pop("encoder"), "'encoder'"),
        ("wm", load_video_model, lambda p: p["state"].pop("model"), "'model'"),
        ("rep", load_encoder, lambda p: p.pop("state"), "'state'"),
        ("rep", load_encoder, lambda p: p.pop("config"), "'config'"),
        ("wm", load_video_model, lambda p: p.pop("kind"), "'kind'"),
        ("wm", load_video_model, lambda p: p["state"]["model"].pop("palette"), "'palette'"),
    ],
    ids=["encoder", "model", "state", "config", "kind", "palette"],
)
def test_a_missing_entry_is_named_with_the_file(trained, tmp_path, kind, loader, edit, missing):
    path = copy_of(trained, kind, tmp_path)
    rewrite_as_format_1(path, edit)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(IntegrityError, match=missing) as info:
            loader(path)
    assert str(path) in str(info.value)


def test_a_trainer_checkpoint_without_rng_states_is_refused(trained, tmp_path, tiny_configs):
    path = copy_of(trained, "rep", tmp_path)
    rewrite_as_format_1(path, lambda p: p["rng"].pop("data"))
    cfg = tiny_configs.representation(path.parent.parent, num_steps=4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(IntegrityError, match="RNG state"):
            RepresentationTrainer(cfg).train(resume=True)


# ---------------------------------------------------------------- resume with another config
@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"lr": 1e-2}, "lr"),
        ({"batch_size": 16}, "batch_size"),
        ({"seed": 3}, "seed"),
        ({"usage_weight": 0.5}, "usage_weight"),
        ({"encoder": {"code_sizes": (16,)}}, "encoder.code_sizes"),
    ],
)
def test_resume_refuses_fields_that_change_the_result(representation_config, changes, field):
    first = RepresentationTrainer(representation_config(num_steps=5))
    first.train()
    good = first.checkpoint_path.read_bytes()
    with pytest.raises(ValueError, match=field) as info:
        RepresentationTrainer(representation_config(num_steps=10, **changes)).train(resume=True)
    assert "checkpoint" in str(info.value) and "now" in str(info.value)
    assert first.checkpoint_path.read_bytes() == good
    assert load_checkpoint(first.checkpoint_path)["step"] == 5


def test_resume_takes_bookkeeping_changes_silently_and_num_steps_with_a_warning(
    representation_config,
):
    full = RepresentationTrainer(representation_config("full", num_steps=10))
    full.train()
    RepresentationTrainer(representation_config("part", num_steps=5)).train()
    resumed = RepresentationTrainer(
        representation_config("part", num_steps=10, checkpoint_every=3, log_every=2)
    )
    with (
        pytest.warns(UserWarning, match=r"num_steps=10 \(checkpoint 5\)") as caught,
        mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step,
    ):
        result = resumed.train(resume=True)
    assert not any("checkpoint_every" in str(w.message) for w in caught)
    assert result["resumed_from_step"] == 5 and step.call_count == 5  # steps 6-10 only
    assert same(state_of(resumed.encoder), state_of(full.encoder))


def test_load_applies_the_trainers_own_learning_rate(trained, representation_config):
    trainer = RepresentationTrainer(representation_config(lr=3e-4))
    trainer.load(trained["rep"])
    assert [g["lr"] for g in trainer.optimizer.param_groups][0] == pytest.approx(3e-4)
    assert same(state_of(trainer.encoder.eval()), trained["rep_weights"])


# ---------------------------------------------------------------- a killed run
def test_a_run_killed_mid_training_resumes_to_the_uninterrupted_weights(representation_config):
    """SIGKILL right after the first checkpoint; the resume must end where an unkilled run does."""
    cfg = representation_config("killed", num_steps=60, checkpoint_every=3, log_every=3)
    code = (
        "import json, sys, torch; torch.set_num_threads(1)\n"
        "from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer\n"
        "RepresentationTrainer(RepresentationConfig.from_dict(json.loads(sys.argv[1]))).train()\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    child = subprocess.Popen([sys.executable, "-c", code, json.dumps(cfg.to_dict())], env=env)
    checkpoint = Path(cfg.out_dir) / "checkpoints" / "last.pt"
    deadline = time.monotonic() + 120
    while not checkpoint.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    child.send_signal(signal.SIGKILL)
    child.wait()
    killed_at = load_checkpoint(checkpoint)["step"]
    assert 3 <= killed_at < 60  # killed mid-run, with a complete checkpoint on disk
    resumed = RepresentationTrainer(cfg)
    with mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step:
        result = resumed.train(resume=True)
    full = RepresentationTrainer(
        representation_config("full", num_steps=60, checkpoint_every=3, log_every=3)
    )
    full.train()
    # It went on from the checkpoint the kill left: that step reported, the later ones trained.
    assert resumed.resumed_from_step == result["resumed_from_step"] == killed_at
    assert step.call_count == 60 - killed_at and resumed.step == 60
    assert logged(cfg.out_dir, "resumed_from") == [(killed_at, f"{float(killed_at)}")]
    assert same(state_of(resumed.encoder), state_of(full.encoder))
    # The log holds the full run's rows: the steps up to the checkpoint once (not trained
    # again), then the resumed ones; only a step logged after the checkpoint, before the
    # kill, may be there twice. Every row has the uninterrupted run's value.
    rows, expected = logged(cfg.out_dir), dict(logged(full.config.out_dir))
    before, after = list(range(3, killed_at + 1, 3)), list(range(killed_at + 3, 61, 3))
    assert [step for step, _ in rows] in (before + after, before + after[:1] + after)
    assert all(value == expected[step] for step, value in rows)
    assert set(expected) == set(range(3, 61, 3))


# ---------------------------------------------------------------- a resume with nothing to resume
@pytest.mark.parametrize("kind", ["representation", "world_model"])
def test_a_resume_without_a_checkpoint_says_so_and_trains_from_step_0(
    kind, representation_config, world_model_config
):
    def make(name: str):
        if kind == "representation":
            return RepresentationTrainer(representation_config(name, num_steps=4))
        return WorldModelTrainer(world_model_config(name, num_steps=4))

    fresh = make("fresh")
    fresh.train()
    assert fresh.resumed_from_step is None  # not a resume
    trainer = make("resumed")
    with (
        pytest.warns(NoCheckpointWarning, match=r"found no checkpoint at .*last\.pt.*step 0"),
        mock.patch.object(trainer, "train_step", wraps=trainer.train_step) as step,
    ):
        result = trainer.train(resume=True)
    assert trainer.resumed_from_step is None and result["resumed_from_step"] is None
    assert step.call_count == 4
    model = trainer.encoder if kind == "representation" else trainer.model
    other = fresh.encoder if kind == "representation" else fresh.model
    assert same(state_of(model), state_of(other))
    # A second resume finds the finished run's checkpoint: nothing to train, its step reported.
    again = make("resumed")
    with (
        mock.patch.object(again, "train_step", wraps=again.train_step) as step,
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("error", NoCheckpointWarning)
        result = again.train(resume=True)
    assert again.resumed_from_step == result["resumed_from_step"] == 4
    assert step.call_count == 0 and result["step"] == 4
