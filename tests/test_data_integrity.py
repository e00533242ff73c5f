"""Play data on disk: what is written to verify them, what loading refuses, what it never touches.

Each test damages a copy of a small complete collection the way a crash, a disk or a
user would, and checks that loading refuses with an ``IntegrityError`` (a
``ValueError``) naming the file, that the damaged files are left exactly as they were
(loading never writes), and that the original collection still loads unchanged.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

import dorp_rl.data.play as play_module
from dorp_rl.data import MATCH_FIELDS, PLAY_KEYS, collect_play_data, load_play_data
from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.integrity import IntegrityError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ARGS = {"num_frames": 300, "seed": 0, "trajectory_length": 10}
METADATA = "play_data.json"


def collect(directory: Path, num_envs: int = 2, **changes) -> object:
    kwargs = ARGS | changes
    return collect_play_data(KeyWallEnv(batch_size=(num_envs,)), directory=directory, **kwargs)


def contents(buffer) -> dict:
    data = buffer[: len(buffer)]
    return {key: data.get(key).clone() for key in PLAY_KEYS}


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file's bytes (what "loading never writes" is checked against)."""
    return {
        p.relative_to(directory).as_posix(): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> tuple[Path, dict]:
    directory = tmp_path_factory.mktemp("integrity") / "keywall"
    return directory, contents(collect(directory))


@pytest.fixture
def copy(original, tmp_path) -> Path:
    target = tmp_path / "copy"
    shutil.copytree(original[0], target)
    return target


def assert_original_still_loads(original) -> None:
    directory, data = original
    loaded = contents(load_play_data(directory))
    for key in PLAY_KEYS:
        assert torch.equal(loaded[key], data[key]), key


# ---------------------------------------------------------------- what is written
def test_metadata_lists_every_stored_file_with_its_size_and_checksum(original):
    directory, _ = original
    meta = json.loads((directory / METADATA).read_text())
    stored = sorted(
        p.relative_to(directory).as_posix()
        for p in (directory / "storage").rglob("*")
        if p.is_file()
    )
    assert sorted(meta["files"]) == stored
    for name, entry in meta["files"].items():
        data = (directory / name).read_bytes()
        assert entry["bytes"] == len(data)
        assert entry["sha256"] == hashlib.sha256(data).hexdigest()
    for key in PLAY_KEYS:
        name = "/".join(key) if isinstance(key, tuple) else key
        assert meta["tensors"][name]["shape"][0] == ARGS["num_frames"]
    assert set(MATCH_FIELDS) <= set(meta)


# ---------------------------------------------------------------- damaged files
def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x01
    path.write_bytes(bytes(data))


def append(path: Path) -> None:
    path.write_bytes(path.read_bytes() + b"\x00" * 8)


def zero(path: Path) -> None:
    path.write_bytes(b"\x00" * path.stat().st_size)


@pytest.mark.parametrize("damage", [truncate, flip, append, zero], ids=lambda f: f.__name__)
@pytest.mark.parametrize(
    "name",
    [
        "storage/pixels.memmap",
        "storage/next/pixels.memmap",
        "storage/action.memmap",
        "storage/state.memmap",
        "storage/next/state.memmap",
        "storage/traj_id.memmap",
        "storage/step_count.memmap",
        "storage/meta.json",
    ],
)
def test_a_damaged_file_is_refused_by_name_and_left_untouched(copy, original, name, damage):
    damage(copy / name)
    before = snapshot(copy)
    with pytest.raises(IntegrityError, match=Path(name).name) as info:
        load_play_data(copy)
    assert isinstance(info.value, ValueError)
    assert str(copy / name) in str(info.value)
    assert snapshot(copy) == before  # the loader neither repaired nor extended anything
    with pytest.raises(IntegrityError):  # collect_play_data loads, so it refuses too
        collect(copy)
    assert snapshot(copy) == before
    assert_original_still_loads(original)


@pytest.mark.parametrize("name", ["storage/next", "storage/state.memmap", "storage"])
def test_a_deleted_file_or_folder_is_refused_by_name(copy, name):
    target = copy / name
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(IntegrityError, match="missing") as info:
        load_play_data(copy)
    assert name in str(info.value)


def test_edited_metadata_is_refused(copy):
    """A one-bit change of the stored seed (0 -> 1) would return seed-0 data for seed 1."""
    meta_path = copy / METADATA
    meta_path.write_text(meta_path.read_text().replace('"seed": 0', '"seed": 1'))
    with pytest.raises(IntegrityError, match=METADATA):
        load_play_data(copy)
    with pytest.raises(IntegrityError, match=METADATA):
        collect(copy, seed=1)


def test_metadata_without_a_play_key_is_refused(copy):
    meta_path = copy / METADATA
    meta = json.loads(meta_path.read_text())
    del meta["tensors"]["next/pixels"]
    meta["metadata_sha256"] = play_module._metadata_digest(meta)  # a consistent forgery
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(IntegrityError, match="next/pixels"):
        load_play_data(copy)


# ---------------------------------------------------------------- loading never writes
def test_changing_a_loaded_buffer_never_reaches_the_files(copy, original):
    before = snapshot(copy)
    buffer = load_play_data(copy)
    extra = buffer[:5].exclude("index").clone()
    extra["pixels"] = torch.full_like(extra["pixels"], 7)
    buffer.extend(extra)  # a full buffer: overwrites its first rows, in memory only
    assert bool((buffer[:5]["pixels"] == 7).all())
    del buffer
    assert snapshot(copy) == before
    assert torch.equal(contents(load_play_data(copy))["pixels"], original[1]["pixels"])


def test_collect_returns_the_data_as_written(tmp_path, original):
    data = contents(collect(tmp_path / "again"))
    for key in PLAY_KEYS:
        assert torch.equal(data[key], original[1][key]), key


# ---------------------------------------------------------------- match check
@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"num_envs": 4}, "num_envs"),
        ({"seed": 1}, "seed"),
        ({"num_frames": 200}, "num_frames"),
        ({"trajectory_length": 5}, "trajectory_length"),
    ],
)
def test_reusing_a_directory_with_other_arguments_names_the_field(copy, changes, field):
    before = snapshot(copy)
    with pytest.raises(ValueError, match=field) as info:
        collect(copy, **changes)
    others = set(MATCH_FIELDS) - {field}
    assert not any(f"{other}:" in str(info.value) for other in others)
    assert snapshot(copy) == before


def test_reusing_a_directory_with_another_env_names_env_config(copy):
    with pytest.raises(ValueError, match="env_config"):
        collect_play_data(
            ObjectRearrangementEnv(num_objects=2, batch_size=(2,)), directory=copy, **ARGS
        )


def test_every_data_changing_argument_is_matched(copy):
    """The device changes the random streams too: another one is refused."""
    stored = load_play_data(copy).metadata
    request = {k: stored[k] for k in MATCH_FIELDS} | {"device": "cuda:0"}
    with pytest.raises(ValueError, match="device: stored 'cpu', requested 'cuda:0'"):
        load_play_data(copy, expected=request)


# ---------------------------------------------------------------- nothing deleted
def test_a_storage_folder_the_library_did_not_write_is_left_alone(tmp_path):
    directory = tmp_path / "mine"
    (directory / "storage").mkdir(parents=True)
    thesis = directory / "storage" / "thesis.txt"
    thesis.write_text("two years of work")
    with pytest.raises(ValueError, match="storage") as info:
        collect(directory)
    assert "did not write" in str(info.value)
    assert thesis.read_text() == "two years of work"
    assert not (directory / METADATA).exists()


def test_files_next_to_a_collection_survive_it(tmp_path):
    directory = tmp_path / "shared"
    directory.mkdir()
    (directory / "notes.txt").write_text("keep me")
    collect(directory)
    assert (directory / "notes.txt").read_text() == "keep me"


def test_an_interrupted_collection_of_the_library_is_redone(copy, original):
    (copy / METADATA).unlink()  # as if killed before sealing: the lock file marks it ours
    truncate(copy / "storage" / "pixels.memmap")
    data = contents(collect(copy))
    for key in PLAY_KEYS:
        assert torch.equal(data[key], original[1][key]), key


def test_directory_naming_a_file_is_refused(tmp_path):
    path = tmp_path / "a-file"
    path.write_text("not a folder")
    with pytest.raises(ValueError, match="directory"):
        collect(path)
    assert path.read_text() == "not a folder"


# ---------------------------------------------------------------- older collections
def as_format_1(directory: Path) -> None:
    meta_path = directory / METADATA
    meta = json.loads(meta_path.read_text())
    for key in ("tensors", "files", "metadata_sha256", "device"):
        del meta[key]
    meta["format_version"] = 1
    meta_path.write_text(json.dumps(meta))


def test_format_1_data_load_with_a_warning(copy, original):
    as_format_1(copy)
    with pytest.warns(UserWarning, match="without checksums"):
        data = contents(load_play_data(copy))
    assert torch.equal(data["pixels"], original[1]["pixels"])


def test_format_1_data_are_still_checked_for_sizes_and_keys(copy):
    as_format_1(copy)
    truncate(copy / "storage" / "pixels.memmap")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(IntegrityError, match="pixels.memmap"):
            load_play_data(copy)
        shutil.rmtree(copy / "storage" / "next")
        with pytest.raises(IntegrityError, match="next"):
            load_play_data(copy)
