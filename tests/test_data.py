"""Tests of the play-data layer, ``dorp_rl.data``: collection, persistence and samplers.

Every stored transition is checked against the environment's own dynamics
(``env.transition``) and renderer (``env.render_state``); trajectory structure is
checked from the stored ``traj_id`` / ``step_count`` columns. Data sets are small and
collected once per module.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, TensorStorage

import dorp_rl.data.play as play_module
from dorp_rl.data import (
    PLAY_KEYS,
    EventWindowSampler,
    FuturePairSampler,
    SequenceSampler,
    UniformRandomPolicy,
    changed_pixels,
    collect_play_data,
    event_transitions,
    future_pairs,
    load_play_data,
    play_env,
    rare_code_changes,
)
from dorp_rl.envs import GridWorldEnv, KeyCorridorEnv, KeyWallEnv, ObjectRearrangementEnv

KEYWALL_DOOR_COLUMN = 8
SHORT_LENGTH = 10  # trajectory length of the short key-wall walks used by sampler tests
METADATA = "play_data.json"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---------------------------------------------------------------------- #
# Helpers
# ---------------------------------------------------------------------- #
def stored(buffer: TensorDictReplayBuffer) -> TensorDict:
    """All stored transitions, without the ``index`` the buffer adds on reads."""
    data = buffer[: len(buffer)]
    return data.exclude("index") if "index" in data.keys() else data


def rebuffer(data: TensorDict, sampler, batch_size: int, generator=None):
    """A fresh in-memory buffer holding ``data`` in the same order, with ``sampler``."""
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(data.shape[0]),
        sampler=sampler,
        batch_size=batch_size,
        generator=generator,
    )
    buffer.extend(data.clone())
    return buffer


def trajectories(data: TensorDict) -> list[torch.Tensor]:
    """Storage indices of each trajectory, in storage order (checks they are contiguous)."""
    traj = data["traj_id"].reshape(len(data))
    runs, counts = torch.unique_consecutive(traj, return_counts=True)
    assert runs.numel() == traj.unique().numel(), "a trajectory is split in storage"
    bounds = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
    return [torch.arange(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def steps(data: TensorDict) -> torch.Tensor:
    return data["step_count"].reshape(len(data))


def check_against_env(env: GridWorldEnv, data: TensorDict) -> None:
    """Layout, dtypes, and every transition against the env's dynamics and renderer."""
    n = len(data)
    for key in PLAY_KEYS:
        assert key in data.keys(include_nested=True), key
    state_shape = tuple(env.state_shape)
    assert data["pixels"].dtype == torch.uint8
    assert data["pixels"].shape == (n, 3, 16, 16)
    assert data["next", "pixels"].dtype == torch.uint8
    assert data["next", "pixels"].shape == (n, 3, 16, 16)
    assert data["state"].dtype == torch.int64
    assert data["state"].shape == (n, *state_shape)
    assert data["next", "state"].shape == (n, *state_shape)
    assert data["action"].dtype == torch.int64
    assert data["action"].shape == (n, 1)
    assert int(data["action"].min()) >= 0
    assert int(data["action"].max()) < env.num_actions
    assert data["step_count"].dtype == torch.int64
    assert data["traj_id"].numel() == n
    assert not env.invalid_states(data["state"]).any()
    expected_next = env.transition(data["state"], data["action"].squeeze(-1))
    assert torch.equal(data["next", "state"], expected_next)
    assert torch.equal(data["pixels"], env.render_state(data["state"]))
    assert torch.equal(data["next", "pixels"], env.render_state(data["next", "state"]))


# ---------------------------------------------------------------------- #
# Shared data sets (collected once)
# ---------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def rearrangement_env() -> ObjectRearrangementEnv:
    return ObjectRearrangementEnv(num_objects=2, batch_size=(16,), seed=0)


@pytest.fixture(scope="module")
def rearrangement_buffer(rearrangement_env) -> TensorDictReplayBuffer:
    return collect_play_data(rearrangement_env, 1000, seed=0)


@pytest.fixture(scope="module")
def keywall_env() -> KeyWallEnv:
    return KeyWallEnv(batch_size=(2,), seed=0)


@pytest.fixture(scope="module")
def keywall_buffer(keywall_env) -> TensorDictReplayBuffer:
    # Two parallel walks of 1000 steps, then the first env's second walk.
    return collect_play_data(keywall_env, 3000, seed=0)


@pytest.fixture(scope="module")
def keycorridor_env() -> KeyCorridorEnv:
    return KeyCorridorEnv(batch_size=(2,), seed=0)


@pytest.fixture(scope="module")
def keycorridor_buffer(keycorridor_env) -> TensorDictReplayBuffer:
    return collect_play_data(keycorridor_env, 3000, seed=0)


@pytest.fixture(scope="module")
def short_buffer(keywall_env) -> TensorDictReplayBuffer:
    """40 key-wall walks of 10 steps, collected with a sampler passed to the collector."""
    return collect_play_data(
        keywall_env,
        400,
        seed=3,
        trajectory_length=SHORT_LENGTH,
        sampler=SequenceSampler(4),
        batch_size=8,
    )


@pytest.fixture(scope="module")
def short_data(short_buffer) -> TensorDict:
    return stored(short_buffer)


@pytest.fixture(scope="module")
def saved_dir(tmp_path_factory) -> tuple[Path, TensorDict]:
    """Key-wall play data persisted to a directory (copy it before damaging it)."""
    directory = tmp_path_factory.mktemp("play") / "keywall"
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 500, directory=directory, seed=0)
    return directory, stored(buffer).clone()


@pytest.fixture
def no_collector(monkeypatch):
    """Makes any attempt to collect fail: whatever passes must have loaded from disk."""

    def refuse(*args, **kwargs):
        raise AssertionError("collect_play_data collected instead of loading")

    monkeypatch.setattr(play_module, "Collector", refuse)


@pytest.fixture
def saved_copy(saved_dir, tmp_path) -> tuple[Path, TensorDict]:
    directory, data = saved_dir
    target = tmp_path / "copy"
    shutil.copytree(directory, target)
    return target, data


# ---------------------------------------------------------------------- #
# Collection: layout and consistency with the env
# ---------------------------------------------------------------------- #
@pytest.mark.parametrize(
    ("env_name", "num_frames"),
    [("rearrangement", 1000), ("keywall", 3000), ("keycorridor", 3000)],
)
def test_play_data_layout_and_dynamics(request, env_name, num_frames):
    env = request.getfixturevalue(f"{env_name}_env")
    buffer = request.getfixturevalue(f"{env_name}_buffer")
    assert isinstance(buffer, TensorDictReplayBuffer)
    assert len(buffer) == num_frames
    assert isinstance(buffer._storage, LazyTensorStorage)
    assert buffer._storage.max_size == num_frames
    check_against_env(env, stored(buffer))


def test_short_data_layout_and_dynamics(keywall_env, short_buffer, short_data):
    assert len(short_buffer) == 400
    check_against_env(keywall_env, short_data)


def test_collection_leaves_the_given_env_untouched():
    env = KeyWallEnv(batch_size=(2,), seed=0)
    before = (env.max_steps, env.terminate_on_success, env.rng.get_state().clone())
    collect_play_data(env, 40, seed=1, trajectory_length=5)
    assert (env.max_steps, env.terminate_on_success) == before[:2]
    assert torch.equal(env.rng.get_state(), before[2])


def test_metadata_describes_the_collection(keywall_env, keywall_buffer, short_buffer):
    meta = keywall_buffer.metadata
    assert meta["env_config"] == keywall_env.config()
    assert meta["num_frames"] == 3000
    assert meta["seed"] == 0
    assert meta["trajectory_length"] == 1000
    assert meta["num_envs"] == 2
    assert short_buffer.metadata["trajectory_length"] == SHORT_LENGTH
    json.dumps(meta)  # JSON-able


# ---------------------------------------------------------------------- #
# Rearrangement: one-step trajectories from fresh random configurations
# ---------------------------------------------------------------------- #
def test_rearrangement_trajectories_have_length_one(rearrangement_buffer):
    data = stored(rearrangement_buffer)
    assert (steps(data) == 0).all()
    traj = data["traj_id"].reshape(-1)
    assert traj.unique().numel() == len(data)


def test_rearrangement_configurations_vary(rearrangement_env, rearrangement_buffer):
    data = stored(rearrangement_buffer)
    states = data["state"].reshape(len(data), -1)
    # ~38k valid 2-block placements: 1000 uniform draws are almost all distinct.
    assert states.unique(dim=0).shape[0] > 900
    # Each transition starts afresh: it rarely continues from the previous one's result.
    continues = (data["state"][1:] == data["next", "state"][:-1]).flatten(1).all(-1)
    assert continues.float().mean() < 0.05
    # Every block is moved in every direction over the data set.
    assert set(data["action"].unique().tolist()) == set(range(rearrangement_env.num_actions))
    # Blocks actually move (not every action is blocked).
    moved = (data["state"] != data["next", "state"]).flatten(1).any(-1)
    assert moved.float().mean() > 0.5


# ---------------------------------------------------------------------- #
# Key rooms: long random walks from random starts
# ---------------------------------------------------------------------- #
def check_random_walks(env, data: TensorDict, length: int, complete: int) -> None:
    runs = trajectories(data)
    lengths = [len(r) for r in runs]
    assert lengths.count(length) >= complete
    assert all(n <= length for n in lengths)
    step = steps(data)
    for rows in runs:
        assert torch.equal(step[rows], torch.arange(len(rows))), "steps 0..L-1 in storage order"
        # A walk: each step starts where the previous one ended.
        assert torch.equal(data["state"][rows[1:]], data["next", "state"][rows[:-1]])
    starts = data["state"][step == 0]
    assert (starts[:, 2] == 0).all(), "walks start without the key"
    assert env.unlocked[starts[:, 0], starts[:, 1]].all(), "walks start in an unlocked room"
    assert not env.key[starts[:, 0], starts[:, 1]].any(), "walks do not start on the key"


def test_keywall_random_walks_of_1000_steps(keywall_env, keywall_buffer):
    data = stored(keywall_buffer)
    check_random_walks(keywall_env, data, 1000, complete=3)
    starts = data["state"][steps(data) == 0]
    assert (starts[:, 1] < KEYWALL_DOOR_COLUMN).all(), "starts in the left room"
    # Distinct start positions and a walk that explores.
    assert starts.unique(dim=0).shape[0] == 3
    first = trajectories(data)[0]
    assert data["state"][first, :2].unique(dim=0).shape[0] > 20
    counts = torch.bincount(data["action"].reshape(-1), minlength=4)
    assert (counts > 0.2 * len(data)).all(), f"actions are not uniform: {counts.tolist()}"


def test_keycorridor_random_walks_of_1500_steps(keycorridor_env, keycorridor_buffer):
    data = stored(keycorridor_buffer)
    check_random_walks(keycorridor_env, data, 1500, complete=2)


def test_trajectory_length_override(keywall_env, short_data):
    check_random_walks(keywall_env, short_data, SHORT_LENGTH, complete=40)
    assert len(trajectories(short_data)) == 40


def test_trajectory_length_override_rearrangement():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
    data = stored(collect_play_data(env, 60, seed=0, trajectory_length=5))
    check_against_env(env, data)
    runs = trajectories(data)
    assert [len(r) for r in runs] == [5] * 12
    for rows in runs:
        assert torch.equal(steps(data)[rows], torch.arange(5))
        assert torch.equal(data["state"][rows[1:]], data["next", "state"][rows[:-1]])


def test_unbatched_env_collects():
    env = KeyWallEnv(seed=0)
    data = stored(collect_play_data(env, 30, seed=0))
    assert len(data) == 30
    assert torch.equal(steps(data), torch.arange(30))
    check_against_env(env, data)


# ---------------------------------------------------------------------- #
# Seeding
# ---------------------------------------------------------------------- #
def test_same_seed_same_data(rearrangement_buffer):
    torch.manual_seed(1234)  # the global RNG must not matter
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(16,), seed=99)
    again = stored(collect_play_data(env, 1000, seed=0))
    first = stored(rearrangement_buffer)
    assert torch.equal(again["pixels"], first["pixels"])
    assert torch.equal(again["action"], first["action"])
    assert torch.equal(again["next", "pixels"], first["next", "pixels"])
    assert torch.equal(again["state"], first["state"])


def test_same_seed_same_walks():
    a = stored(collect_play_data(KeyWallEnv(batch_size=(2,), seed=1), 200, seed=5))
    torch.manual_seed(77)
    b = stored(collect_play_data(KeyWallEnv(batch_size=(2,), seed=2), 200, seed=5))
    assert torch.equal(a["pixels"], b["pixels"])
    assert torch.equal(a["action"], b["action"])
    assert torch.equal(a["next", "state"], b["next", "state"])


def test_other_seed_other_data(rearrangement_buffer, keywall_buffer):
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(16,), seed=0)
    other = stored(collect_play_data(env, 1000, seed=1))
    first = stored(rearrangement_buffer)
    assert not torch.equal(other["pixels"], first["pixels"])
    assert not torch.equal(other["action"], first["action"])
    # Not merely shifted: most transitions differ.
    assert (other["state"] != first["state"]).flatten(1).any(-1).float().mean() > 0.9

    walk = stored(collect_play_data(KeyWallEnv(batch_size=(2,), seed=0), 200, seed=1))
    base = stored(keywall_buffer)
    assert not torch.equal(walk["action"][:100], base["action"][:100])
    assert not torch.equal(walk["state"][[0, 100]], base["state"][[0, 1000]])


def test_uniform_random_policy():
    td = TensorDict(batch_size=(5000,))
    a = UniformRandomPolicy(6, seed=0)(td.clone())["action"]
    torch.manual_seed(3)
    b = UniformRandomPolicy(6, seed=0)(td.clone())["action"]
    c = UniformRandomPolicy(6, seed=1)(td.clone())["action"]
    assert a.shape == (5000, 1) and a.dtype == torch.int64
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    counts = torch.bincount(a.reshape(-1), minlength=6)
    assert counts.numel() == 6 and (counts > 700).all()


def test_play_env_is_a_configured_copy():
    env = KeyCorridorEnv(batch_size=(3,), seed=0)
    out = play_env(env)
    assert out is not env
    assert out.max_steps == 1500 and not out.terminate_on_success
    assert env.max_steps == 800 and env.terminate_on_success
    assert play_env(KeyWallEnv(batch_size=(3,))).max_steps == 1000
    assert play_env(ObjectRearrangementEnv(num_objects=3, batch_size=(3,))).max_steps == 1
    assert play_env(env, trajectory_length=7).max_steps == 7


# ---------------------------------------------------------------------- #
# Persistence
# ---------------------------------------------------------------------- #
def test_saved_data_is_memory_mapped_in_the_directory(saved_dir):
    directory, data = saved_dir
    assert (directory / METADATA).is_file()
    assert (directory / "storage").is_dir()
    assert any((directory / "storage").rglob("*.memmap"))
    assert len(data) == 500
    check_against_env(KeyWallEnv(), data)


def test_second_call_loads_instead_of_collecting(saved_dir, no_collector):
    directory, data = saved_dir
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 500, directory=directory, seed=0)
    # Loaded copy-on-write from the files in the directory (see test_data_integrity.py).
    assert isinstance(buffer._storage, TensorStorage)
    assert len(buffer) == 500
    loaded = stored(buffer)
    for key in PLAY_KEYS:
        assert torch.equal(loaded[key], data[key]), key
    assert buffer.metadata == json.loads((directory / METADATA).read_text())


def test_second_call_accepts_str_directory_and_sampler(saved_dir, no_collector):
    directory, data = saved_dir
    buffer = collect_play_data(
        KeyWallEnv(batch_size=(2,)),
        500,
        directory=str(directory),
        seed=0,
        sampler=FuturePairSampler(1, 3),
        batch_size=8,
    )
    anchor, future, offset = future_pairs(buffer.sample(8))
    assert anchor.shape == future.shape == (8, 3, 16, 16)
    assert ((offset >= 1) & (offset <= 3)).all()


def test_reload_honours_the_requested_batch_size(saved_dir, no_collector):
    directory, _ = saved_dir
    buffer = collect_play_data(
        KeyWallEnv(batch_size=(2,)),
        500,
        directory=directory,
        seed=0,
        sampler=FuturePairSampler(1, 3),
        batch_size=8,
    )
    assert buffer.sample().shape == (8, 2)
    assert load_play_data(directory, batch_size=5).sample().shape == (5,)


def test_load_play_data(saved_dir):
    directory, data = saved_dir
    buffer = load_play_data(directory)
    assert len(buffer) == 500
    assert torch.equal(stored(buffer)["pixels"], data["pixels"])
    assert torch.equal(stored(buffer)["action"], data["action"])
    assert buffer.metadata["num_frames"] == 500
    seq = load_play_data(directory, sampler=SequenceSampler(3), batch_size=5)
    assert seq.sample(5)["action"].shape == (5, 3, 1)
    with pytest.raises(ValueError, match="seed"):
        load_play_data(directory, expected={"seed": 4})


@pytest.mark.parametrize(
    ("change", "entry"),
    [
        ({"seed": 1}, "seed"),
        ({"num_frames": 400}, "num_frames"),
        ({"env": KeyCorridorEnv}, "env_config"),
        ({"env": lambda **kw: ObjectRearrangementEnv(num_objects=2, **kw)}, "env_config"),
        ({"trajectory_length": 50}, "trajectory_length"),
    ],
    ids=["seed", "num_frames", "env", "env2", "trajectory_length"],
)
def test_mismatching_request_raises(saved_dir, no_collector, change, entry):
    directory, _ = saved_dir
    # trajectory_length is pinned so that only the changed entry differs.
    kwargs = {"num_frames": 500, "seed": 0, "env": KeyWallEnv, "trajectory_length": 1000} | change
    env = kwargs.pop("env")(batch_size=(2,))
    with pytest.raises(ValueError, match=entry) as info:
        collect_play_data(env, directory=directory, **kwargs)
    assert "stored" in str(info.value) and "requested" in str(info.value)
    # Only the differing entry is named.
    for other in {"seed", "num_frames", "env_config", "trajectory_length"} - {entry}:
        assert other not in str(info.value)


@pytest.mark.parametrize("text", ["{not json", "", "\x00\x01garbage"])
def test_corrupted_metadata_raises(saved_copy, no_collector, text):
    directory, _ = saved_copy
    (directory / METADATA).write_text(text)
    with pytest.raises(ValueError, match="corrupted"):
        load_play_data(directory)
    with pytest.raises(ValueError):
        collect_play_data(KeyWallEnv(batch_size=(2,)), 500, directory=directory, seed=0)


@pytest.mark.parametrize("text", ["[]", "null", "42", '{"format_version": 1}'])
def test_well_formed_json_that_is_not_play_metadata_raises(saved_copy, no_collector, text):
    directory, _ = saved_copy
    (directory / METADATA).write_text(text)
    with pytest.raises(ValueError):
        load_play_data(directory)


def test_wrong_format_version_raises(saved_copy):
    directory, _ = saved_copy
    meta = json.loads((directory / METADATA).read_text())
    meta["format_version"] = 999
    (directory / METADATA).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format_version"):
        load_play_data(directory)


def test_frame_count_disagreeing_with_metadata_raises(saved_copy):
    directory, _ = saved_copy
    meta = json.loads((directory / METADATA).read_text())
    meta["num_frames"] = 600
    (directory / METADATA).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="600"):
        load_play_data(directory)


def test_missing_directory_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match="no play data"):
        load_play_data(tmp_path / "does-not-exist")
    with pytest.raises(FileNotFoundError):
        load_play_data(tmp_path)  # exists, holds nothing


def test_deleted_metadata_means_no_play_data(saved_copy, no_collector):
    directory, _ = saved_copy
    (directory / METADATA).unlink()
    with pytest.raises(FileNotFoundError, match="no play data"):
        load_play_data(directory)
    # collect_play_data does not trust the orphaned storage: it tries to collect.
    with pytest.raises(AssertionError, match="collected instead of loading"):
        collect_play_data(KeyWallEnv(batch_size=(2,)), 500, directory=directory, seed=0)


def test_recollect_after_deleted_metadata(saved_copy):
    """An interrupted collection leaves storage without metadata; collecting again must work."""
    directory, data = saved_copy
    (directory / METADATA).unlink()
    buffer = collect_play_data(KeyWallEnv(batch_size=(2,)), 500, directory=directory, seed=0)
    assert torch.equal(stored(buffer)["pixels"], data["pixels"])
    assert (directory / METADATA).is_file()
    assert torch.equal(stored(load_play_data(directory))["action"], data["action"])


# ---------------------------------------------------------------------- #
# FuturePairSampler
# ---------------------------------------------------------------------- #
def test_future_pairs_never_cross_trajectories(keywall_env, short_data):
    buffer = rebuffer(short_data, FuturePairSampler(1, SHORT_LENGTH), 4000)
    sample = buffer.sample()
    assert sample.shape == (4000, 2)
    index = sample["index"]
    offset = sample[:, 0]["offset"]
    traj = short_data["traj_id"].reshape(-1)
    step = steps(short_data)
    assert torch.equal(traj[index[:, 0]], traj[index[:, 1]])
    assert torch.equal(step[index[:, 1]] - step[index[:, 0]], offset - 1)
    assert torch.equal(index[:, 1] - index[:, 0], offset - 1)
    # The future observation is exactly `offset` steps of the stored actions away.
    state = short_data["state"][index[:, 0]]
    for j in range(SHORT_LENGTH):
        active = offset > j
        rows = index[:, 0] + j
        nxt = keywall_env.transition(
            state, short_data["action"][rows.clamp(max=len(step) - 1)][:, 0]
        )
        state = torch.where(active.unsqueeze(-1), nxt, state)
    assert torch.equal(state, short_data["next", "state"][index[:, 1]])


def test_future_pair_offsets_cover_the_range(short_data):
    buffer = rebuffer(short_data, FuturePairSampler(2, 6), 3000)
    offset = buffer.sample()[:, 0]["offset"]
    assert int(offset.min()) >= 2 and int(offset.max()) <= 6
    counts = torch.bincount(offset, minlength=7)[2:]
    assert (counts > 0.7 * 3000 / 5).all(), counts.tolist()


def test_future_pair_offsets_beyond_trajectories_are_refused(short_data):
    """A max_offset no stored trajectory reaches is refused, naming the offset and the
    longest trajectory (it used to draw the shorter offsets only, without a word)."""
    with pytest.raises(ValueError, match=rf"offset 40 needs 40 .* holds {SHORT_LENGTH}\b"):
        rebuffer(short_data, FuturePairSampler(8, 40), 500).sample()
    with pytest.raises(ValueError, match=rf"offset {SHORT_LENGTH + 1} .* holds {SHORT_LENGTH}\b"):
        rebuffer(short_data, FuturePairSampler(1, SHORT_LENGTH + 1), 500).sample()
    # Up to the trajectory length, every offset of the range is drawn, the longest too.
    sample = rebuffer(short_data, FuturePairSampler(8, SHORT_LENGTH), 500).sample()
    offset = sample[:, 0]["offset"]
    assert set(offset.tolist()) == set(range(8, SHORT_LENGTH + 1))
    traj = short_data["traj_id"].reshape(-1)
    assert torch.equal(traj[sample["index"][:, 0]], traj[sample["index"][:, 1]])


def test_future_pairs_unpacks_anchor_and_future(keywall_buffer):
    data = stored(keywall_buffer)
    buffer = rebuffer(data, FuturePairSampler(1, 50), 64)
    sample = buffer.sample()
    anchor, future, offset = future_pairs(sample)
    assert anchor.shape == (64, 3, 16, 16) and anchor.dtype == torch.uint8
    assert future.shape == (64, 3, 16, 16) and future.dtype == torch.uint8
    assert offset.shape == (64,)
    index = sample["index"]
    assert torch.equal(anchor, data["pixels"][index[:, 0]])
    assert torch.equal(future, data["next", "pixels"][index[:, 1]])
    assert torch.equal(index[:, 1] - index[:, 0], offset - 1)
    with pytest.raises(ValueError, match=r"\[B, 2\]"):
        future_pairs(sample[:, :1])
    with pytest.raises(ValueError):
        future_pairs(sample[:, 0])


def test_future_pairs_on_rearrangement_data(rearrangement_buffer):
    data = stored(rearrangement_buffer)
    one = rebuffer(data, FuturePairSampler(1), 32)
    anchor, future, offset = future_pairs(one.sample())
    assert (offset == 1).all()
    assert anchor.shape == (32, 3, 16, 16)
    # One-step trajectories: FuturePairSampler(1, 4) is refused, not silently k = 1.
    for low in (1, 2):
        with pytest.raises(ValueError, match=r"offset 4 needs 4 .* holds 1\b"):
            rebuffer(data, FuturePairSampler(min_offset=low, max_offset=4), 8).sample()


@pytest.mark.parametrize(("low", "high"), [(0, 3), (-1, None), (0, None), (3, 2), (5, 1)])
def test_invalid_offsets_raise(low, high):
    with pytest.raises(ValueError, match="min_offset"):
        FuturePairSampler(low, high)


def test_future_pair_sampler_default_max_is_min(short_data):
    sampler = FuturePairSampler(3)
    assert (sampler.min_offset, sampler.max_offset) == (3, 3)
    assert (rebuffer(short_data, sampler, 50).sample()[:, 0]["offset"] == 3).all()


def test_samplers_use_the_buffer_generator(short_data):
    for make in (lambda: FuturePairSampler(1, 5), lambda: SequenceSampler(4)):
        draws = []
        for seed, global_seed in [(0, 1), (0, 2), (1, 1)]:
            buffer = rebuffer(short_data, make(), 64, generator=torch.Generator().manual_seed(seed))
            torch.manual_seed(global_seed)  # must not matter
            draws.append(torch.cat([buffer.sample()["index"] for _ in range(3)]))
        assert torch.equal(draws[0], draws[1])
        assert not torch.equal(draws[0], draws[2])
        # set_rng after construction works too.
        buffer = rebuffer(short_data, make(), 64)
        buffer.set_rng(torch.Generator().manual_seed(0))
        assert torch.equal(torch.cat([buffer.sample()["index"] for _ in range(3)]), draws[0])


def synthetic(lengths: list[int], first_id: int = 0) -> TensorDict:
    traj = torch.cat([torch.full((n,), first_id + i) for i, n in enumerate(lengths)])
    step = torch.cat([torch.arange(n) for n in lengths])
    return TensorDict(
        traj_id=traj,
        step_count=step.unsqueeze(-1),
        obs=torch.arange(len(traj)),
        batch_size=[len(traj)],
    )


def test_samplers_follow_overwritten_storage():
    """Valid windows are recomputed when a full (circular) storage is overwritten."""
    pair = TensorDictReplayBuffer(
        storage=LazyTensorStorage(40), sampler=FuturePairSampler(8, 10), batch_size=200
    )
    seq = TensorDictReplayBuffer(
        storage=LazyTensorStorage(40), sampler=SequenceSampler(8), batch_size=200
    )
    for buffer in (pair, seq):
        buffer.extend(synthetic([10, 10, 10, 10]))
        buffer.sample()
        buffer.extend(synthetic([5] * 8, first_id=100))  # same length, shorter walks
        assert len(buffer) == 40
        with pytest.raises(ValueError):
            buffer.sample()
        buffer.extend(synthetic([3, 10, 10, 10, 6, 1], first_id=200))
        sample = buffer.sample()
        index = sample["index"]
        assert (sample["traj_id"] == sample["traj_id"][:, :1]).all()
        step = sample["step_count"].squeeze(-1)
        assert torch.equal(step[:, -1] - step[:, 0], index[:, -1] - index[:, 0])
        assert set(sample["traj_id"].unique().tolist()) == {201, 202, 203}  # 204 is too short


def test_samplers_name_missing_keys():
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(10), sampler=SequenceSampler(2), batch_size=4
    )
    buffer.extend(synthetic([10]).exclude("traj_id"))
    with pytest.raises(KeyError, match="traj_id"):
        buffer.sample()


# ---------------------------------------------------------------------- #
# SequenceSampler
# ---------------------------------------------------------------------- #
def test_sequence_windows_from_collector(keywall_env, short_buffer, short_data):
    horizon, batch = 4, 8
    sample = short_buffer.sample()
    assert sample.shape == (batch, horizon)
    assert sample["action"].shape == (batch, horizon, 1)
    assert sample["pixels"].shape == (batch, horizon, 3, 16, 16)
    assert sample["next", "pixels"].shape == (batch, horizon, 3, 16, 16)


def test_sequence_windows_are_consecutive_steps(keywall_env, short_data):
    horizon = 6
    sample = rebuffer(short_data, SequenceSampler(horizon), 2000).sample()
    index = sample["index"]
    assert torch.equal(index - index[:, :1], torch.arange(horizon).expand_as(index))
    assert (sample["traj_id"] == sample["traj_id"][:, :1]).all()
    step = sample["step_count"].squeeze(-1)
    assert torch.equal(step - step[:, :1], torch.arange(horizon).expand_as(step))
    assert sample["action"].shape == (2000, horizon, 1)
    assert sample["next", "pixels"].shape == (2000, horizon, 3, 16, 16)
    assert torch.equal(sample["next", "pixels"][:, :-1], sample["pixels"][:, 1:])
    assert torch.equal(sample["next", "state"][:, :-1], sample["state"][:, 1:])
    expected = keywall_env.transition(sample["state"], sample["action"].squeeze(-1))
    assert torch.equal(sample["next", "state"], expected)
    # Every window start that fits is reachable (starts 0..L-H within each walk).
    assert set(step[:, 0].unique().tolist()) == set(range(SHORT_LENGTH - horizon + 1))


def test_sequence_horizon_equal_to_trajectory_length(short_data):
    sample = rebuffer(short_data, SequenceSampler(SHORT_LENGTH), 100).sample()
    assert (sample["step_count"][:, 0] == 0).all()
    assert (sample["traj_id"] == sample["traj_id"][:, :1]).all()


def test_sequence_too_long_for_trajectories_raises(short_data, rearrangement_buffer):
    buffer = rebuffer(short_data, SequenceSampler(SHORT_LENGTH + 1), 4)
    with pytest.raises(ValueError, match="trajectory_length") as info:
        buffer.sample()
    assert str(SHORT_LENGTH + 1) in str(info.value)
    one_step = rebuffer(stored(rearrangement_buffer), SequenceSampler(2), 4)
    with pytest.raises(ValueError, match="horizon"):
        one_step.sample()
    # Horizon 1 is fine on one-step data.
    assert rebuffer(stored(rearrangement_buffer), SequenceSampler(1), 4).sample().shape == (4, 1)


@pytest.mark.parametrize("horizon", [0, -2])
def test_sequence_bad_horizon_raises(horizon):
    with pytest.raises(ValueError, match="horizon"):
        SequenceSampler(horizon)


# ---------------------------------------------------------------------- #
# EventWindowSampler
# ---------------------------------------------------------------------- #
def walk_with_events(length: int, events: list[int]) -> TensorDict:
    """One walk of ``length`` steps: each step moves one pixel (2 cells change), except the
    ``events``, which also change 3 more cells (like a door opening)."""
    pixels = torch.zeros(length + 1, 3, 16, 16, dtype=torch.uint8)
    for t in range(length + 1):
        pixels[t, 0, t % 16, (t // 16) % 16] = 255
    nxt = pixels[1:].clone()
    for t in events:
        nxt[t, 1, 15, 13:] = 200
    return TensorDict(
        traj_id=torch.zeros(length, dtype=torch.int64),
        step_count=torch.arange(length).unsqueeze(-1),
        pixels=pixels[:-1],
        next=TensorDict(pixels=nxt, batch_size=[length]),
        batch_size=[length],
    )


def event_share_of(sample: TensorDict) -> float:
    """Share of the ``[B, H]`` windows of ``sample`` holding a transition changing > 2 cells."""
    cells = (sample["pixels"] != sample["next", "pixels"]).any(-3).flatten(-2).sum(-1)
    return float((cells > 2).any(-1).float().mean())


def test_event_transitions_are_the_key_pickups_of_key_wall_play(keywall_buffer):
    data = stored(keywall_buffer)
    events = event_transitions(changed_pixels(keywall_buffer.storage))
    key_taken = data["next", "state"][:, 2] != data["state"][:, 2]
    assert key_taken.sum() >= 1  # the seeded walks take the key twice
    assert torch.equal(events, key_taken)


def test_event_transitions_threshold():
    changed = torch.tensor([0, 0, 4, 8, 4, 8, 8, 0])
    assert event_transitions(changed).tolist() == [False] * 8  # 8 is the ordinary move
    assert event_transitions(changed, min_changed=5).tolist() == [c >= 5 for c in changed]
    assert not event_transitions(torch.zeros(5, dtype=torch.int64)).any()


def test_event_window_sampler_draws_the_requested_share_of_event_windows():
    horizon, data = 4, walk_with_events(400, [100, 300])
    event_starts = set(range(97, 101)) | set(range(297, 301))  # 8 of 397 windows
    generator = torch.Generator().manual_seed(0)
    uniform = rebuffer(data, SequenceSampler(horizon), 4000, generator=generator).sample()
    assert event_share_of(uniform) < 0.05
    sampler = EventWindowSampler(horizon, event_share=0.5)
    sample = rebuffer(data, sampler, 4000, generator=generator).sample()
    assert 0.45 < event_share_of(sample) < 0.55
    starts, has_event = sampler.window_events(rebuffer(data, sampler, 1).storage)
    assert set(starts[has_event].tolist()) == event_starts
    drawn = set(sample["index"][:, 0].tolist())
    assert event_starts <= drawn and len(drawn - event_starts) > 300  # the others too
    index = sample["index"]
    assert torch.equal(index - index[:, :1], torch.arange(horizon).expand_as(index))
    # A share below the natural one leaves sampling uniform.
    natural = rebuffer(data, EventWindowSampler(horizon, 0.0), 4000, generator=generator)
    assert event_share_of(natural.sample()) < 0.05
    # Seeded by the buffer's generator.
    again = rebuffer(data, EventWindowSampler(horizon, 0.5), 64, torch.Generator().manual_seed(3))
    other = rebuffer(data, EventWindowSampler(horizon, 0.5), 64, torch.Generator().manual_seed(3))
    assert torch.equal(again.sample()["index"], other.sample()["index"])


def test_event_window_sampler_without_events_is_uniform_and_says_so():
    data = walk_with_events(50, [])
    buffer = rebuffer(data, EventWindowSampler(4, event_share=0.5), 32)
    with pytest.warns(UserWarning, match="none of the 47 windows holds an event"):
        assert buffer.sample().shape == (32, 4)


def test_event_window_sampler_takes_its_events_from_a_function():
    horizon, data = 4, walk_with_events(400, [])
    marked = torch.zeros(400, dtype=torch.bool)
    marked[[50, 250]] = True
    sampler = EventWindowSampler(horizon, 0.5, events=lambda storage: marked[: len(storage)])
    buffer = rebuffer(data, sampler, 4000, generator=torch.Generator().manual_seed(0))
    starts, has_event = sampler.window_events(buffer.storage)
    assert set(starts[has_event].tolist()) == set(range(47, 51)) | set(range(247, 251))
    first = buffer.sample()["index"][:, 0]
    assert (
        0.45
        < ((first >= 47) & (first <= 50) | (first >= 247) & (first <= 250)).float().mean()
        < 0.55
    )
    wrong = rebuffer(data, EventWindowSampler(horizon, 0.5, events=lambda s: marked[:10]), 8)
    with pytest.raises(ValueError, match=r"bool \[400\] \(one flag per stored transition\)"):
        wrong.sample()
    with pytest.raises(ValueError, match="not both"):
        EventWindowSampler(horizon, 0.5, min_changed=3, events=lambda s: marked)
    with pytest.raises(ValueError, match="function of the storage"):
        EventWindowSampler(horizon, 0.5, events=marked)


def test_rare_code_changes_are_changes_of_rarely_changing_one_hots():
    codes = torch.zeros(100, 3, dtype=torch.int64)
    nxt = codes.clone()
    nxt[::2, 0] = 1  # one-hot 0 changes on half the transitions
    nxt[[3, 7], 1] = 1  # one-hot 1 on 2%: rare
    nxt[1::4, 2] = 1  # one-hot 2 on a quarter: not rare at ratio 0.1
    events = rare_code_changes(codes, nxt)
    assert events.nonzero().flatten().tolist() == [3, 7]
    assert rare_code_changes(codes, nxt, ratio=0.5).sum() == 2 + 25
    with pytest.raises(ValueError, match=r"\[N, K\]"):
        rare_code_changes(codes, nxt[:, :2])


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_event_window_sampler_bad_share_raises(share):
    with pytest.raises(ValueError, match="event_share"):
        EventWindowSampler(4, event_share=share)


# ---------------------------------------------------------------------- #
# Bad input
# ---------------------------------------------------------------------- #
@pytest.mark.parametrize("num_frames", [0, -5])
def test_bad_num_frames_raises(num_frames, tmp_path):
    with pytest.raises(ValueError, match="num_frames"):
        collect_play_data(KeyWallEnv(batch_size=(2,)), num_frames)
    with pytest.raises(ValueError, match="num_frames"):
        collect_play_data(KeyWallEnv(batch_size=(2,)), num_frames, directory=tmp_path / "d")
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("env", [object(), "KeyWallEnv", None])
def test_what_is_not_a_torchrl_env_raises(env):
    with pytest.raises(ValueError, match="must be a TorchRL EnvBase"):
        collect_play_data(env, 10)
    with pytest.raises(ValueError, match="must be a TorchRL EnvBase"):
        play_env(env)


def test_a_torchrl_env_without_images_raises_naming_its_observations():
    pytest.importorskip("gymnasium")
    from torchrl.envs.libs.gym import GymEnv

    env = GymEnv("CartPole-v1")
    with pytest.raises(ValueError, match=r"no image observation 'pixels'; .*'observation'"):
        collect_play_data(env, 10, trajectory_length=5)


@pytest.mark.parametrize("length", [0, -1])
def test_bad_trajectory_length_raises(length):
    with pytest.raises(ValueError, match="trajectory_length"):
        collect_play_data(KeyWallEnv(batch_size=(2,)), 10, trajectory_length=length)


def test_unlocked_env_raises():
    with pytest.raises(ValueError, match="batch"):
        collect_play_data(KeyWallEnv(batch_locked=False), 10)
