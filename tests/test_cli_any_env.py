"""The ``dorp`` command on envs written in the tests, named by an import path."""

from __future__ import annotations

import json

import pytest
import torch
from push_blocks import PushBlocksEnv

from dorp_rl.cli import main
from dorp_rl.envs import env_identity
from dorp_rl.planners import CodeGraph
from dorp_rl.trainers import load_encoder

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = (
    "--codes.num-frames", "400",
    "--codes.num-envs", "8",
    "--codes.num-steps", "5",
    "--codes.batch-size", "16",
    "--codes.diagnostics-samples", "64",
    "--tasks", "3",
    "--tasks-per-rollout", "3",
    "--candidates", "20",
    "--planning-horizon", "3",
    "--max-steps", "5",
    "--gifs", "1",
    "--no-progress",
)  # fmt: skip


def test_evaluate_an_env_given_by_import_path_through_every_stage(tmp_path):
    main(
        [
            "evaluate",
            "--root",
            str(tmp_path),
            "--name",
            "pb",
            "--env",
            "push_blocks:PUSH_BLOCKS",
            *TINY,
        ]
    )
    run = tmp_path / "pb"
    stages = json.loads((run / "stages.json").read_text())
    assert {"play", "codes", "graph", "evaluate:dorp:gt", "pictures"} <= set(stages)
    # The profile maps states to block cells: purity per one-hot, from this env's play.
    codes = stages["codes"]["summary"]
    assert len(codes["purity"]) == 2 and all(0.0 < p <= 1.0 for p in codes["purity"])
    assert 0.0 <= codes["selectivity"] <= 1.0
    assert stages["play"]["summary"]["frames"] == 400
    # The profile's play trajectories (20 steps) and code preset (two one-hots of 6).
    assert stages["play"]["config"]["env"] == "push_blocks:PUSH_BLOCKS"
    row = stages["evaluate:dorp:gt"]["summary"]
    assert row["setting"] == "push_blocks:PUSH_BLOCKS" and row["tasks"] == 3
    # The profile's lower bound (Manhattan distance) is each task's bound.
    assert all(b >= 1 for b in row["per_task"]["lower_bound"])
    assert all(s <= 5 for s in row["per_task"]["steps"])

    env = PushBlocksEnv((3, 24, 32), batch_size=(4,))
    encoder = load_encoder(run / "codes" / "checkpoints" / "last.pt", env)
    assert encoder.frame_shape == (3, 24, 32) and tuple(encoder.code_sizes) == (6, 6)
    assert encoder.env_config == env_identity(env)
    graph = CodeGraph.load(run / "graph.pt", encoder=encoder, env_config=env_identity(env))
    assert graph.num_groups == 2
    # Codes and graph of this env are refused against another env.
    other = PushBlocksEnv((1, 8, 8), batch_size=(4,))
    with pytest.raises(ValueError, match="another|environment"):
        load_encoder(run / "codes" / "checkpoints" / "last.pt", other)
    with pytest.raises(ValueError, match="environment"):
        CodeGraph.load(run / "graph.pt", encoder=encoder, env_config=env_identity(other))
    assert (run / "pictures" / "rollout_0.gif").exists()
    # No ground-truth pictures for an env that declares no state-to-objects diagnostics.
    assert not (run / "pictures" / "code_map.png").exists()


def test_a_minimal_profile_of_an_env_reading_step_count_through_every_stage(tmp_path):
    # The profile gives make_env, a lower bound and object labels; the number of one-hots,
    # the map competition, the exclusivity and the maps' stride are chosen and logged.
    argv = ["evaluate", "--root", str(tmp_path), "--name", "cp", "--env", "counting_pieces:PROFILE"]
    tiny = [a for a in TINY if a not in ("--gifs", "1")]
    main([*argv, *tiny, "--codes.trajectory-length", "4"])
    run = tmp_path / "cp"
    stages = json.loads((run / "stages.json").read_text())
    chosen = stages["codes"]["summary"]["chosen"]
    assert chosen == {
        "num_onehots": 2,
        "encoder.map_competition": "softmax",
        "exclusivity_weight": 3.0,
        "encoder.subtract_background": False,  # black background: nothing to subtract
        "encoder.map_stride": 1,
    }
    log = (run / "log.txt").read_text()
    assert "codes: chose num_onehots = 2 (2 pieces move in a play frame" in log
    assert len(stages["codes"]["summary"]["purity"]) == 2
    # the graph's groups are read from the play data's codes, logged and recorded
    assert "graph: chose groups = " in log
    groups = stages["graph"]["summary"]["groups"]
    assert sorted(i for g in groups for i in g) == [0, 1]
    # DORP planned through the env's own dynamics, which read step_count at every step.
    row = stages["evaluate:dorp:gt"]["summary"]
    assert row["tasks"] == 3 and all(s <= 5 for s in row["per_task"]["steps"])


def test_a_gray_8x8_env_with_one_hot_actions_through_the_command(tmp_path):
    """A bare factory (no profile): the generic defaults, one one-hot of 32 codes."""
    main(
        [
            "evaluate",
            "--root",
            str(tmp_path),
            "--name",
            "gray",
            "--env",
            "push_blocks:make_small_env",
            *TINY,
        ]
    )
    stages = json.loads((tmp_path / "gray" / "stages.json").read_text())
    row = stages["evaluate:dorp:gt"]["summary"]
    assert row["tasks"] == 3 and len(row["per_task"]["success"]) == 3
    # No lower bound is known for a bare factory: recorded as unknown, not made up.
    assert all(b != b for b in row["per_task"]["lower_bound"])  # nan
    encoder = load_encoder(tmp_path / "gray" / "codes" / "checkpoints" / "last.pt")
    assert encoder.frame_shape == (1, 8, 8)
    # the play length was chosen from the env's resets, and said
    log = (tmp_path / "gray" / "log.txt").read_text()
    assert "play: chose trajectory_length = " in log
    assert stages["play"]["summary"]["chosen"]["trajectory_length"] in (1, 100)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--env", "push_blocks:PUSH_BLOCKS", "--setting", "1obj"], "--env and --setting both"),
        (["--env", "no_such_module_xyz:make_env"], "cannot import"),
        (["--env", "push_blocks:nothing_here"], "has no attribute"),
        (["--env", "push_blocks:MOVES"], "must be an EnvProfile or a function"),
    ],
)
def test_a_bad_env_is_a_usage_error_naming_it(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as stop:
        main(["collect", "--root", str(tmp_path), "--name", "bad", *argv, "--no-progress"])
    assert stop.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "bad" / "stages.json").exists()


def test_object_diagnostics_tell_factorized_codes_from_swapped_and_constant_ones():
    from dorp_rl.eval import object_diagnostics

    g = torch.Generator().manual_seed(0)
    pos = torch.randint(0, 9, (400, 2), generator=g)
    nxt = pos.clone()
    mover = torch.randint(0, 2, (400,), generator=g)
    nxt[torch.arange(400), mover] = torch.randint(0, 9, (400,), generator=g)
    # One-hot 0 codes object 1's cell, one-hot 1 object 0's in 3-cell regions.
    codes = torch.stack([pos[:, 1], pos[:, 0] // 3], -1)
    next_codes = torch.stack([nxt[:, 1], nxt[:, 0] // 3], -1)
    good = object_diagnostics(codes, next_codes, pos, nxt)
    assert good["onehot_object"] == [1, 0] and good["min_purity"] == 1.0
    assert good["selectivity"] == 1.0
    # Codes that ignore the objects: no place predicts them; changes land anywhere.
    noise = torch.randint(0, 9, (400, 2), generator=g)
    flat = object_diagnostics(noise, torch.randint(0, 9, (400, 2), generator=g), pos, nxt)
    assert flat["min_purity"] < 0.6 and flat["selectivity"] < 0.7
    with pytest.raises(ValueError, match="must match in shape"):
        object_diagnostics(codes, next_codes[:, :1], pos, nxt)


def test_the_dead_two_code_onehot_is_reported(tmp_path):
    """A two-code one-hot that never changes along play is reported dead (with a warning)."""
    from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer

    cfg = RepresentationConfig.for_env(
        "push_blocks:PUSH_BLOCKS",
        encoder={"code_sizes": (6, 2)},
        num_frames=400,
        num_envs=8,
        num_steps=3,
        batch_size=16,
        diagnostics_samples=64,
        out_dir=str(tmp_path / "codes"),
        progress=False,
    )
    trainer = RepresentationTrainer(cfg)
    for p in trainer.encoder.parameters():  # every frame gets the same codes
        torch.nn.init.zeros_(p)
    result = trainer.evaluate()
    assert trainer.encoder.code_sizes[1] == 2  # the two-code one-hot is not left out
    assert result["dead_onehots"] == [0, 1]
    assert result["code_dynamics"]["codes_used"] == [1, 1]


def test_a_minigrid_env_through_torchrl_gym_wrapper_to_codes_and_graph(tmp_path, monkeypatch):
    """MiniGrid DoorKey (examples/gymnasium_env.py): its renderer's 3 x 24 x 24 frames and
    5 of its actions through torchrl's GymWrapper and SerialEnv, by the command."""
    pytest.importorskip("minigrid")
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples"))
    argv = [
        "build-graph",
        "--root",
        str(tmp_path),
        "--name",
        "mg",
        "--env",
        "gymnasium_env:GYM_PROFILE",
    ]
    main([*argv, "--codes.num-frames", "400", "--codes.num-envs", "4", "--codes.num-steps", "3",
          "--codes.batch-size", "16", "--codes.diagnostics-samples", "64", "--no-progress"])  # fmt: skip
    stages = json.loads((tmp_path / "mg" / "stages.json").read_text())
    assert stages["play"]["summary"]["frames"] == 400
    assert stages["graph"]["summary"]["nodes"][0] >= 1
    encoder = load_encoder(tmp_path / "mg" / "codes" / "checkpoints" / "last.pt")
    import gymnasium_env

    # No recipe in the profile: one-hots of the default 32 codes, as many as were chosen.
    chosen = stages["codes"]["summary"]["chosen"]
    side = gymnasium_env.SIZE * gymnasium_env.TILE_SIZE
    assert encoder.frame_shape == (3, side, side)
    assert tuple(encoder.code_sizes) == (32,) * chosen["num_onehots"]
    from dorp_rl.data import load_play_data

    play = load_play_data(tmp_path / "mg" / "play")[:400]
    assert play["action"].shape == (400, 5)  # GymWrapper's one-hot actions, 5 of them
    assert play["pixels"].dtype == torch.uint8 and play["pixels"].shape[1:] == (3, side, side)


def _door_key(monkeypatch):
    pytest.importorskip("minigrid")
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples"))
    import gymnasium_env

    return gymnasium_env


def test_minigrid_as_a_goal_env_copied_or_set_steps_as_minigrid_does(monkeypatch):
    """GymGoalEnv over MiniGrid: with set_state and copy-only (snapshots), the same
    transitions as MiniGrid itself, each (state, action) stepped in MiniGrid once."""
    from dorp_rl.envs import GymGoalEnv

    door_key = _door_key(monkeypatch)
    by_setting = door_key.make_env(batch_size=(), seed=0)
    by_copying = GymGoalEnv(door_key.make_door_key_gym, door_key.door_key_state, batch_size=())
    states = by_setting.reachable_states()
    assert states == by_copying.reachable_states()
    # Agent poses (7 cells x 4 directions) times key and door states: far fewer than 1000.
    assert 28 <= len(states) < 200
    # Against MiniGrid stepped by hand from its reset: pickup needs facing the key, etc.
    gym_env = door_key.make_door_key_gym()
    gym_env.reset()
    state = torch.tensor(door_key.door_key_state(gym_env))
    g = torch.Generator().manual_seed(0)
    for _ in range(40):
        action = int(torch.randint(0, 5, (1,), generator=g))
        gym_env.step(action)
        expected = torch.tensor(door_key.door_key_state(gym_env))
        for env in (by_setting, by_copying):
            assert torch.equal(env.transition(state, torch.tensor(action)), expected)
        frame = torch.from_numpy(gym_env.render()).permute(2, 0, 1)
        assert torch.equal(by_setting.render_states(expected), frame)
        state = expected
    calls = by_setting.dynamics.gym_calls
    batch = torch.tensor(states[:5]).unsqueeze(1).expand(5, 200, -1)
    actions = torch.randint(0, 5, (5, 200), generator=g)
    by_setting.transition(batch, actions)
    assert by_setting.dynamics.gym_calls == calls  # all remembered: no MiniGrid call
    # A never-seen state cannot be copied from.
    with pytest.raises(ValueError, match="was never reached"):
        by_copying.transition(torch.tensor([3, 3, 0, 0, 0]), torch.tensor(0))


def test_dorp_on_minigrid_through_the_command(tmp_path, monkeypatch):
    _door_key(monkeypatch)
    argv = ["evaluate", "--root", str(tmp_path), "--name", "dk", "--env", "gymnasium_env:PROFILE"]
    main([*argv, *TINY])
    stages = json.loads((tmp_path / "dk" / "stages.json").read_text())
    row = stages["evaluate:dorp:gt"]["summary"]
    # Exact lower bounds by breadth-first search over MiniGrid's own dynamics.
    assert row["tasks"] == 3 and all(b >= 1 for b in row["per_task"]["lower_bound"])
    # purity of every one-hot by the profile's objects
    encoder = load_encoder(tmp_path / "dk" / "codes" / "checkpoints" / "last.pt")
    assert len(stages["codes"]["summary"]["purity"]) == len(encoder.code_sizes)


def test_minigrid_door_key_events_count_pickups_and_toggles_apart(monkeypatch):
    """The example's events: a pickup is a key event, a toggle a door event; the example
    prints which one-hots each kind of event changed."""
    from dorp_rl.metrics.diagnostics import object_diagnostics

    door_key = _door_key(monkeypatch)
    # states: agent x, y, direction, key carried, door (0 locked, 1 closed, 2 open)
    state = torch.tensor([[1, 1, 0, 0, 0], [1, 1, 0, 1, 0], [2, 2, 0, 1, 1], [2, 2, 0, 1, 2]])
    nxt = torch.tensor([[1, 1, 0, 1, 0], [1, 1, 0, 1, 0], [2, 2, 0, 1, 2], [2, 2, 0, 1, 1]])
    # codes (agent, key): the pickup changes both one-hots; the first toggle changes the
    # key one-hot, the second (open -> closed) changes nothing
    codes = torch.tensor([[0, 0], [0, 1], [3, 2], [3, 3]])
    next_codes = torch.tensor([[1, 1], [0, 1], [3, 3], [3, 3]])
    labelled = object_diagnostics(
        codes, next_codes, door_key.door_key_events(state), door_key.door_key_events(nxt)
    )
    assert labelled["moves_per_object"][1:3] == [1, 2]  # one pickup, two toggles
    assert list(labelled["change_matrix"][1]) == [1, 1]  # the pickup changed both one-hots
    assert list(labelled["change_matrix"][2]) == [0, 1]  # one toggle changed the key one-hot
    # The profile's objects put the key and the door on one object of 4 situations.
    situations = door_key.PROFILE.objects(torch.cat([state, nxt]))[:, 1]
    assert sorted(set(situations.tolist())) == [0, 3, 4, 5]
