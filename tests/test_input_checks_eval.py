"""Input checks of the code graph, the task sets and evaluators, the play-data samplers and
the world-model config: inputs that cannot be right are refused by name.

Each class of input goes through every entry point that takes it (bad codes through every
graph query, bad task sets through both evaluators, too-long windows through sampling,
collecting and loading). Every refusal is a ``ValueError`` whose message names the
argument or field and what it must be.
"""

from __future__ import annotations

import math
import re

import pytest
import torch
from tensordict import TensorDict, TensorDictBase

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.data import (
    EventWindowSampler,
    FuturePairSampler,
    SequenceSampler,
    collect_play_data,
    load_play_data,
    play_segment_length,
)
from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import (
    EvalSpec,
    check_task_set,
    evaluate_parallel,
    evaluate_policy,
    make_task_set,
)
from dorp_rl.eval.tasks import summarize
from dorp_rl.integrity import IntegrityError
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.modules.video import VideoModelConfig
from dorp_rl.planners import CodeGraph, encode_transitions
from dorp_rl.trainers import WorldModelConfig, WorldModelTrainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def two_object_play():
    return collect_play_data(ObjectRearrangementEnv(num_objects=2, batch_size=(8,)), 256, seed=0)


@pytest.fixture(scope="module")
def key_wall_play():
    return collect_play_data(KeyWallEnv(batch_size=(2,)), 256, seed=0)


@pytest.fixture(scope="module")
def graph() -> CodeGraph:
    """Two one-hots of 4 codes; group 0 holds nodes 0..2, group 1 nodes 3..4."""
    codes = torch.tensor([[0, 0], [1, 0], [1, 1], [2, 1]])
    return CodeGraph.from_transitions(codes[:-1], codes[1:], code_sizes=(4, 4))


# --------------------------------------------------------------------------- code graph
def test_an_encoder_of_another_setting_is_refused_naming_both_envs(two_object_play, key_wall_play):
    two = ObjectRearrangementEnv(num_objects=2)
    cases = [
        # a 1-object encoder over 2-object play data (the example)
        (two_object_play, OracleCodeEncoder(ObjectRearrangementEnv(num_objects=1))),
        (two_object_play, DiscreteCodeEncoder(EncoderConfig.small((8,)))),
        (two_object_play, DiscreteCodeEncoder(EncoderConfig.small((8, 8, 8)))),
        (key_wall_play, OracleCodeEncoder(two)),
        (key_wall_play, DiscreteCodeEncoder(EncoderConfig.small((8, 8)))),
    ]
    for play, encoder in cases:
        wanted = "num_objects=2" if play is two_object_play else "KeyWallEnv"
        sizes = re.escape(str(tuple(encoder.code_sizes)))
        for entry_point in (CodeGraph.from_play_data, encode_transitions):
            with pytest.raises(ValueError, match=rf"sizes {sizes}.*play data come from .*{wanted}"):
                entry_point(play, encoder)
    # The codes given as transitions do not get round the check.
    one = OracleCodeEncoder(ObjectRearrangementEnv(num_objects=1))
    codes = torch.zeros(len(two_object_play), 1, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"sizes \(16,\).*num_objects=2"):
        CodeGraph.from_play_data(two_object_play, one, transitions=(codes, codes))
    # A key-room oracle has the 2-object layout (16 x 16 cells, a key bit), but records
    # the env it encodes.
    with pytest.raises(ValueError, match="trained on KeyWallEnv.*num_objects=2"):
        CodeGraph.from_play_data(two_object_play, OracleCodeEncoder(KeyWallEnv()))
    # The right encoder builds the graph.
    assert CodeGraph.from_play_data(two_object_play, OracleCodeEncoder(two)).num_groups == 2


def test_an_encoder_that_records_its_env_must_record_the_play_datas(two_object_play, tmp_path):
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8, 8)))
    other = ObjectRearrangementEnv(num_objects=2, block_shapes=(2, 2))
    encoder.env_config = other.config()
    with pytest.raises(ValueError, match="trained on ObjectRearrangementEnv.*block_shapes"):
        CodeGraph.from_play_data(two_object_play, encoder)
    encoder.env_config = two_object_play.metadata["env_config"]
    graph = CodeGraph.from_play_data(two_object_play, encoder)
    path = graph.save(tmp_path / "graph.pt")
    assert CodeGraph.load(path, encoder=encoder).num_groups == 2
    encoder.env_config = other.config()
    with pytest.raises(ValueError, match="encoder was trained on .*block_shapes"):
        CodeGraph.load(path, encoder=encoder)


@pytest.mark.parametrize("chunk_size", [0, -4, 2.5, True, "8", None])
def test_chunk_size_must_be_an_integer_of_at_least_one(two_object_play, chunk_size):
    oracle = OracleCodeEncoder(ObjectRearrangementEnv(num_objects=2))
    for call in (CodeGraph.from_play_data, encode_transitions):
        with pytest.raises(ValueError, match="chunk_size must be"):
            call(two_object_play, oracle, chunk_size=chunk_size)


def test_small_chunks_encode_the_same_codes(two_object_play):
    oracle = OracleCodeEncoder(ObjectRearrangementEnv(num_objects=2))
    whole = encode_transitions(two_object_play, oracle)
    chunked = encode_transitions(two_object_play, oracle, chunk_size=7)
    assert all(torch.equal(a, b) for a, b in zip(whole, chunked, strict=True))


BAD_NODE_IDS = [(-1, r"-1"), (0.5, r"0\.5"), (True, "True"), (99, "99")]


@pytest.mark.parametrize(("value", "shown"), BAD_NODE_IDS)
def test_node_ids_must_be_integer_nodes_in_range(graph, value, shown):
    """The issue: shortest_path(0, -1, 1) returned [] and shortest_path(0, 0.5, 1) truncated."""
    group0 = r"node id of group 0 \(an integer in \[0, 2\]\)"
    calls = {
        "start": (lambda: graph.shortest_path(0, value, 1), group0),
        "goal": (lambda: graph.shortest_path(0, 1, value), group0),
        "node": (lambda: graph.next_waypoint(value, 2), r"in \[0, 4\]"),
        "goal ": (lambda: graph.next_waypoint(0, value), r"in \[0, 4\]"),
        "goal  ": (lambda: graph.distances_to(value), r"in \[0, 4\]"),
        "stop_at": (lambda: graph.distances_to(2, stop_at=value), group0),
        "node ": (lambda: graph.node_code(value), r"in \[0, 4\]"),
        "node  ": (lambda: graph.neighbours(value), r"in \[0, 4\]"),
        "a": (lambda: graph.edge_id(value, 1), r"in \[0, 4\]"),
        "b": (lambda: graph.edge_id(0, value), r"in \[0, 4\]"),
    }
    for name, (call, allowed) in calls.items():
        with pytest.raises(ValueError, match=rf"^{name.strip()} must be .*{allowed}.*{shown}"):
            call()


def test_a_node_of_another_group_is_refused(graph):
    with pytest.raises(ValueError, match=r"start must be a node id of group 1 .*\[3, 4\]"):
        graph.shortest_path(1, 0, 3)
    with pytest.raises(ValueError, match=r"stop_at must be a node id of group 0"):
        graph.distances_to(0, stop_at=3)


@pytest.mark.parametrize("group", [-1, 2, 0.5, True, "0"])
def test_group_indices_must_be_integers_in_range(graph, group):
    code = torch.tensor([0, 0])
    calls = [
        lambda: graph.shortest_path(group, code, code),
        lambda: graph.node_of(code, group),
        lambda: graph.group_keys(code, group),
        lambda: graph.num_nodes(group),
        lambda: graph.num_edges(group),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=r"^group must be .*\[0, 1\]"):
            call()
    with pytest.raises(ValueError, match=r"^onehot must be .*\[0, 1\]"):
        graph.group_of(group)


@pytest.mark.parametrize(
    ("code", "message"),
    [
        (torch.tensor([4, 0]), r"code 4 for one-hot 0, which has codes 0\.\.3"),
        (torch.tensor([0, -1]), r"code -1 for one-hot 1, which has codes 0\.\.3"),
        (torch.tensor([0.0, 1.0]), "integer tensor"),
        (torch.tensor([True, False]), "integer tensor"),
        (torch.tensor([0, 0, 0]), "must have 2 codes"),
    ],
)
def test_codes_must_be_integers_within_the_code_sizes(graph, code, message):
    """A code out of range would alias another joint code of its group."""
    good = torch.tensor([0, 0])
    for name, call in (
        ("start", lambda: graph.shortest_path(0, code, good)),
        ("goal", lambda: graph.shortest_path(0, good, code)),
        ("code", lambda: graph.node_of(code, 0)),
        ("code", lambda: graph.group_keys(code, 1)),
    ):
        with pytest.raises(ValueError, match=rf"^{name} .*{message}"):
            call()
    with pytest.raises(ValueError, match="start must be a code"):
        graph.shortest_path(0, good[None], good)  # [1, C]: neither a code nor a node id


def test_removed_and_edge_ids_must_be_integer_edges(graph):
    edges = graph.indices.shape[0]
    for removed in (torch.tensor([edges]), torch.tensor([-2])):
        with pytest.raises(ValueError, match=rf"removed ids must lie in -1\.\.{edges - 1}"):
            graph.next_waypoint(0, 2, removed)
        with pytest.raises(ValueError, match="removed ids must lie in"):
            graph.shortest_path(0, 0, 2, removed)
    for call in (
        lambda: graph.distances_to(2, torch.tensor([0.0])),
        lambda: graph.group_of_edge(torch.tensor([0.5])),
    ):
        with pytest.raises(ValueError, match="ids must be integers"):
            call()
    with pytest.raises(ValueError, match="removed must be an integer tensor"):
        graph.distances_to(2, [0])
    # -1 entries are the padding of the policy's per-row lists, and mean no edge.
    assert graph.shortest_path(0, 0, 2, torch.tensor([-1, -1])) == [0, 1, 2]


def _rewrite_graph(path, tmp_path, change):
    payload = load_checkpoint(path, kind="code_graph")
    config = change(dict(payload["config"]))
    return save_checkpoint(
        tmp_path / "changed.pt",
        kind="code_graph",
        config=config,
        env_config=payload["env_config"],
        state=payload["state"],
        step=0,
    )


def test_a_graph_file_with_an_unknown_config_field_is_refused(graph, tmp_path):
    path = graph.save(tmp_path / "graph.pt")
    extra = _rewrite_graph(path, tmp_path, lambda c: {**c, "max_hops": 3})
    with pytest.raises(ValueError, match=r"unknown CodeGraphConfig fields \['max_hops'\]"):
        CodeGraph.load(extra)
    # The same refusal as an encoder or world-model config of another version.
    with pytest.raises(ValueError, match=r"unknown WorldModelConfig fields \['max_hops'\]"):
        WorldModelConfig.from_dict({**WorldModelConfig().to_dict(), "max_hops": 3})
    without = _rewrite_graph(
        path, tmp_path, lambda c: {k: v for k, v in c.items() if k != "groups"}
    )
    with pytest.raises(IntegrityError, match=r"incomplete: missing \['groups'\]"):
        CodeGraph.load(without)
    bad = _rewrite_graph(path, tmp_path, lambda c: {**c, "dense_limit": -1})
    with pytest.raises(ValueError, match="dense_limit must be >= 0"):
        CodeGraph.load(bad)
    assert CodeGraph.load(path).config() == graph.config()


# --------------------------------------------------------------------------- task sets
def greedy(td: TensorDictBase) -> TensorDictBase:
    """Moves the single block toward its goal; at the goal it moves right anyway."""
    diff = td["goal_state"][..., 0, :] - td["state"][..., 0, :]
    action = torch.where(
        diff[..., 0] != 0,
        torch.where(diff[..., 0] < 0, 0, 1),
        torch.where(diff[..., 1] < 0, 2, 3),
    )
    td["action"] = action.unsqueeze(-1).to(torch.int64)
    return td


def always_right(td: TensorDictBase) -> TensorDictBase:
    td["action"] = torch.full((*td.batch_size, 1), 3, dtype=torch.int64)
    return td


@pytest.mark.parametrize("env", ["env", None, 4, TensorDict()])
def test_make_task_set_needs_an_env(env):
    with pytest.raises(ValueError, match="env must be a TorchRL EnvBase"):
        make_task_set(env, 4)


def test_evaluators_need_an_env_and_a_policy():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(), batch_locked=False)
    tasks = make_task_set(env, 2, seed=0)
    for policy in ("random", None, 3):
        with pytest.raises(ValueError, match="policy must be a TensorDict policy"):
            evaluate_policy(env, policy, tasks)
    with pytest.raises(ValueError, match="env must be a TorchRL EnvBase"):
        evaluate_policy("env", greedy, tasks)
    spec = EvalSpec("1obj", "random")
    with pytest.raises(ValueError, match="make_env must be a callable"):
        evaluate_parallel("1obj", spec.make_policy, tasks)
    with pytest.raises(ValueError, match="make_policy must be a callable"):
        evaluate_parallel(spec.make_env, "random", tasks)
    with pytest.raises(ValueError, match=r"the env of make_env\(\) must be a TorchRL EnvBase"):
        evaluate_parallel(lambda: "env", spec.make_policy, tasks, workers=2)


def _bad_task_sets() -> dict[str, tuple[object, str]]:
    env = ObjectRearrangementEnv(num_objects=1)
    tasks = make_task_set(env, 3, seed=0)
    off_grid, negative, nan, two_objects = tasks.clone(), tasks.clone(), tasks.clone(), None
    off_grid["goal_state"][1] = torch.tensor([[20, 3]])
    negative["lower_bound"][2] = -1
    nan.set("lower_bound", tasks["lower_bound"].double())
    nan["lower_bound"][0] = math.nan
    two_objects = make_task_set(ObjectRearrangementEnv(num_objects=2), 3, seed=0)
    return {
        "empty": (tasks[:0], "tasks is empty"),
        "negative bound": (negative, r"lower_bound'\] must hold finite step counts >= 0.*-1"),
        "nan bound": (nan, r"lower_bound'\] must hold finite step counts >= 0.*nan"),
        "goal off the grid": (off_grid, r"tasks\['goal_state'\] holds 1 invalid.*16x16 grid"),
        "another env's states": (two_objects, r"tasks\['state'\] must have shape \[\*B, 1, 2\]"),
        "no goal": (tasks.exclude("goal_state"), "tasks must hold 'goal_state'"),
        "two batch dims": (tasks.unsqueeze(0), r"one batch dimension \[num_tasks\]"),
        "a dict": ({"state": tasks["state"]}, "tasks must be a TensorDict of tasks"),
    }


@pytest.mark.parametrize("case", list(_bad_task_sets()))
def test_bad_task_sets_are_refused_by_both_evaluators(case):
    tasks, message = _bad_task_sets()[case]
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(), batch_locked=False)
    spec = EvalSpec("1obj", "random")
    calls = [
        lambda: evaluate_policy(env, greedy, tasks),
        lambda: evaluate_policy(env, greedy, tasks, seed=0, tasks_per_rollout=2),
        lambda: check_task_set(tasks, env),
        # Several workers: refused before any worker process starts.
        lambda: evaluate_parallel(spec.make_env, spec.make_policy, tasks, workers=2),
    ]
    if case not in ("goal off the grid", "another env's states"):  # needs the env to see it
        calls.append(lambda: evaluate_parallel(spec.make_env, spec.make_policy, tasks))
    for call in calls:
        with pytest.raises(ValueError, match=message):
            call()


def test_an_empty_result_is_not_summarised_as_nan():
    tasks = make_task_set(ObjectRearrangementEnv(num_objects=1), 2, seed=0)[:0]
    with pytest.raises(ValueError, match="at least one task"):
        summarize(tasks, [], [], max_steps=5, seconds=0.0)


class _UnreachableGoals(ObjectRearrangementEnv):
    """An env whose bound says some goals cannot be reached (-1, as the key rooms' BFS would)."""

    def lower_bound_steps(self, state: torch.Tensor, goal_state: torch.Tensor) -> torch.Tensor:
        bound = super().lower_bound_steps(state, goal_state)
        return torch.where(bound % 3 == 0, torch.full_like(bound, -1), bound)


def test_make_task_set_refuses_negative_lower_bounds():
    with pytest.raises(ValueError, match=r"lower_bound'\] must hold finite step counts >= 0"):
        make_task_set(_UnreachableGoals(num_objects=1), 20, seed=0)


def _with_goal_at_start(tasks: TensorDictBase, rows: list[int]) -> TensorDictBase:
    tasks = tasks.clone()
    for row in rows:
        tasks["goal_state"][row] = tasks["state"][row]
        tasks["lower_bound"][row] = 0
    return tasks


@pytest.mark.parametrize(("batch_size", "per_rollout"), [((), 1), ((), 3), ((4,), 4)])
def test_a_task_starting_at_its_goal_is_solved_at_step_zero(batch_size, per_rollout):
    """The greedy policy moves right at the goal: the first action would leave it."""
    env = ObjectRearrangementEnv(
        num_objects=1, batch_size=batch_size, batch_locked=bool(batch_size)
    )
    tasks = _with_goal_at_start(make_task_set(env, 6, seed=0), [1, 5])
    result = evaluate_policy(env, greedy, tasks, tasks_per_rollout=per_rollout, seed=0)
    expected = tasks["lower_bound"].tolist()
    assert expected[1] == expected[5] == 0 and min(expected[:1] + expected[2:5]) > 0
    assert result["success"] == [True] * 6
    assert result["steps"] == expected


def test_a_chunk_solved_at_its_start_reports_step_zero():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,))
    tasks = _with_goal_at_start(make_task_set(env, 2, seed=0), [0, 1])
    result = evaluate_policy(
        env, always_right, tasks, tasks_per_rollout=2, report_keys=("step_count",)
    )
    assert result["success"] == [True, True] and result["steps"] == [0, 0]
    assert result["step_count"] == [0.0, 0.0]
    assert result["success_rate"] == 1.0 and result["mean_steps"] == 0.0


def test_evaluate_parallel_counts_a_task_at_its_goal_as_solved_at_step_zero():
    spec = EvalSpec("1obj", "random", seed=0)
    tasks = _with_goal_at_start(make_task_set(spec.make_env(), 3, seed=0), [1])
    assert int(tasks["lower_bound"][2]) > 3  # out of reach of 3 steps
    run = {"seed": 0, "max_steps": 3, "tasks_per_rollout": 1}
    for workers in (1, 2):
        result = evaluate_parallel(spec.make_env, spec.make_policy, tasks, workers=workers, **run)
        assert result["workers"] == workers
        assert result["success"][1] is True and result["steps"][1] == 0
        # An ordinary task more than 3 steps away is not solved.
        assert result["success"][2] is False and result["steps"][2] == 3


# --------------------------------------------------------------------------- samplers
def test_a_pair_sampler_longer_than_the_trajectories_is_refused_everywhere(tmp_path):
    """FuturePairSampler(1, 4) over one-step trajectories: refused, never k = 1 only."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,))
    with pytest.raises(ValueError, match=r"FuturePairSampler spans 4 .* 1 step\(s\) long"):
        collect_play_data(env, 64, sampler=FuturePairSampler(1, 4))
    collect_play_data(env, 64, directory=tmp_path / "play")
    with pytest.raises(ValueError, match=r"FuturePairSampler spans 4 .* 1 step\(s\) long"):
        load_play_data(tmp_path / "play", sampler=FuturePairSampler(1, 4))
    with pytest.raises(ValueError, match=r"FuturePairSampler spans 4"):
        collect_play_data(env, 64, directory=tmp_path / "play", sampler=FuturePairSampler(1, 4))
    buffer = load_play_data(tmp_path / "play", sampler=FuturePairSampler(1))
    buffer.set_sampler(FuturePairSampler(1, 4))  # set afterwards: refused when sampling
    with pytest.raises(ValueError, match=r"pair of offset 4 needs 4 .* holds 1\b"):
        buffer.sample(8)


@pytest.mark.filterwarnings("ignore:EventWindowSampler. none of the")  # 33 frames: no key
@pytest.mark.parametrize(
    "sampler", [SequenceSampler(5), EventWindowSampler(5, 0.5), FuturePairSampler(2, 5)]
)
def test_windows_longer_than_each_envs_share_of_the_frames_are_refused(sampler):
    """8 envs and 32 frames store 4 steps of each 1000-step walk: no 5-step window."""
    env = KeyWallEnv(batch_size=(8,))
    assert play_segment_length(32, 8, 1000) == 4
    with pytest.raises(ValueError, match=r"spans 5 .*num_frames=32 over 8 envs .* 4 consecutive"):
        collect_play_data(env, 32, sampler=sampler)
    buffer = collect_play_data(env, 33, sampler=sampler, batch_size=4)  # 5 steps of env 0
    assert buffer.sample().shape[:1] == (4,)


@pytest.mark.parametrize(
    ("frames", "envs", "length", "expected"),
    [(100_000, 64, 16, 16), (32, 16, 4, 2), (33, 16, 4, 3), (5, 1, 1000, 5), (9, 4, 1, 1)],
)
def test_play_segment_length_is_the_longest_stored_run(frames, envs, length, expected):
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(envs,))
    assert play_segment_length(frames, envs, length) == expected
    if frames <= 64:  # what collect_play_data stores
        buffer = collect_play_data(env, frames, trajectory_length=length)
        assert SequenceSampler(1).longest_run(buffer.storage) == expected


# --------------------------------------------------------------------------- world model
def tiny_world_model(tmp_path, **overrides) -> WorldModelConfig:
    values = {
        "num_steps": 1,
        "num_frames": 256,
        "num_envs": 16,
        "horizon": 3,
        "trajectory_length": 4,
        "eval_frames": 128,
        "eval_sequences": 4,
        "model": VideoModelConfig.small(),
        "progress": False,
        "out_dir": str(tmp_path / "wm"),
        **overrides,
    }
    return WorldModelConfig.for_env("rearrangement", 1, **values)


@pytest.mark.parametrize("field", ["eval_frames", "num_frames"])
def test_too_few_frames_for_the_windows_name_the_field_and_its_least_value(tmp_path, field):
    """16 envs, windows of 3 steps: each env must store 3 steps, so 2 * 16 + 1 = 33 frames."""
    message = (
        rf"^{field} \(32\) must be at least 33 for windows of horizon 3: .*num_envs=16 .*"
        r"ceil\(" + field + r" / num_envs\) = 2 consecutive steps"
    )
    with pytest.raises(ValueError, match=message):
        tiny_world_model(tmp_path, **{field: 32})
    base = tiny_world_model(tmp_path)
    with pytest.raises(ValueError, match=message):
        base.replace(**{field: 32})
    with pytest.raises(ValueError, match=message):
        WorldModelConfig.from_dict({**base.to_dict(), field: 32})
    # The same frames fit fewer envs or shorter windows.
    tiny_world_model(tmp_path, **{field: 32, "num_envs": 8})
    tiny_world_model(tmp_path, **{field: 32, "horizon": 2})
    # At the bound itself the trainer finds its windows (a bound of the right size).
    trainer = WorldModelTrainer(tiny_world_model(tmp_path, **{field: 33}))
    assert trainer.eval_windows.shape == (4, 3)
    assert trainer.buffer.sample().shape == (trainer.config.batch_size, 3)
