"""Actions that change nothing: the planners' excluded first actions, and the DORP
policy's rule that stops a learned model's blocked move from being planned again."""

from __future__ import annotations

import pytest
import torch

from dorp_rl.data import collect_play_data
from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeGraph,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import NOOPS_KEY, AbstractGoalPolicy, AvoidNoops, make_dorp_policy
from dorp_rl.validation import MissingKeyError

SMALL = {"num_candidates": 64, "planning_horizon": 6}


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def planner_of(kind, env, **kwargs):
    return kind(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        planning_horizon=6,
        num_candidates=50,
        seed=0,
        **kwargs,
    )


@pytest.mark.parametrize("kind", [RandomShootingPlanner, CategoricalCEMPlanner])
def test_planners_start_no_candidate_with_an_excluded_action(kind) -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    planner = planner_of(kind, env, excluded_actions_key="excluded")
    assert "excluded" in planner.in_keys
    td = env.reset()
    # Row 0 may start only with action 2; row 1 with anything but 0 and 1.
    td["excluded"] = torch.tensor([[True, True, False, True], [True, True, False, False]])
    seen = []
    evaluate = planner._evaluate

    def spy(sub, decisions):
        seen.append(decisions.clone())
        return evaluate(sub, decisions)

    planner._evaluate = spy
    out = planner(td)
    firsts = torch.cat([d[..., 0] for d in seen if d.shape[1] == 50], 1)  # not the pruning
    assert (firsts[0] == 2).all()
    assert set(firsts[1].unique().tolist()) <= {2, 3}
    assert out["planner_plan"][0, 0] == 2 and out["planner_plan"][1, 0] in (2, 3)
    # Scored directly, a candidate starting with an excluded action costs inf.
    decisions = torch.tensor([[[0, 1, 2, 3, 0, 1], [2, 2, 2, 2, 2, 2]]] * 2)
    score, _ = evaluate(td, decisions)
    assert torch.isinf(score[:, 0]).all() and torch.isfinite(score[:, 1]).all()


@pytest.mark.parametrize("kind", [RandomShootingPlanner, CategoricalCEMPlanner])
def test_excluding_nothing_plans_as_a_planner_without_the_key(kind) -> None:
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(3,), seed=1)
    td = env.reset()
    plain = planner_of(kind, env)(td.clone())
    td["excluded"] = torch.zeros(3, 8, dtype=torch.bool)
    keyed = planner_of(kind, env, excluded_actions_key="excluded")(td)
    assert torch.equal(plain["planner_plan"], keyed["planner_plan"])


def test_a_missing_or_bad_exclusion_is_refused() -> None:
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    planner = planner_of(RandomShootingPlanner, env, excluded_actions_key="excluded")
    with pytest.raises(MissingKeyError, match="may not start with from 'excluded'"):
        planner(env.reset())
    for bad, message in (
        (torch.zeros(2, 4), "must hold bool \\[4\\] per row.*torch.float32"),
        (torch.zeros(2, 3, dtype=torch.bool), "must hold bool \\[4\\] per row.*\\[2, 3\\]"),
    ):
        with pytest.raises(ValueError, match=message):
            planner(env.reset().set("excluded", bad))


@pytest.fixture(scope="module")
def one_object():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
    return env, oracle, graph


def test_the_rule_is_on_with_a_learned_low_level_and_off_with_the_true_dynamics(one_object):
    env, oracle, graph = one_object
    true = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    assert true.config.avoid_noops is False
    assert NOOPS_KEY not in true.state_keys
    assert true.waypoint_planner.excluded_actions_key is None
    # Any planning env given as the low level may mispredict (a learned model): on.
    learned = make_dorp_policy(env, oracle, graph, low_level=GroundTruthModelEnv(env), **SMALL)
    assert learned.config.avoid_noops is True
    assert any(isinstance(rule, AvoidNoops) for rule in learned.rules)
    for planner in (learned.waypoint_planner, learned.goal_planner):
        assert planner.excluded_actions_key == NOOPS_KEY
    off = make_dorp_policy(
        env, oracle, graph, low_level=GroundTruthModelEnv(env), avoid_noops=False
    )
    assert NOOPS_KEY not in off.state_keys
    forced = make_dorp_policy(env, oracle, graph, avoid_noops=True, **SMALL)
    assert NOOPS_KEY in forced.state_keys
    with pytest.raises(ValueError, match="AvoidNoops needs planners that read 'dorp_noops'"):
        AbstractGoalPolicy(
            oracle,
            graph,
            true.waypoint_planner,
            true.goal_planner,
            true.config,
            rules=[AvoidNoops()],
        )


def test_an_action_that_changed_nothing_is_not_planned_again_until_the_frame_changes(
    one_object,
):
    env, oracle, graph = one_object
    policy = make_dorp_policy(env, oracle, graph, avoid_noops=True, seed=0, **SMALL)
    td = env.reset()
    tried = []
    for step in range(4):  # the env is never stepped: every action changed nothing
        td = policy(td)
        action = int(td["action"].reshape(-1)[0])
        assert action not in tried
        tried.append(action)
        assert td[NOOPS_KEY][0].nonzero().squeeze(-1).tolist() == sorted(tried[:-1])
        if step:  # each unchanged frame made the planner plan afresh
            waypoint = int(td["dorp_mode"][0, 0]) == 1
            planner = policy.waypoint_planner if waypoint else policy.goal_planner
            assert int(td[planner.cursor_key][0, 0]) == 1
    assert sorted(tried) == [0, 1, 2, 3]
    # All four excluded: a plan still comes (every candidate scores inf).
    td = policy(td)
    assert td[NOOPS_KEY].all()
    # A frame that changed clears the memory.
    other = env.reset()
    while torch.equal(other["pixels"], td["pixels"]):
        other = env.reset()
    for key in policy.state_keys:
        other[key] = td[key]
    other = policy(other)
    assert not other[NOOPS_KEY].any()
    # Back at the first frame, its four unchanging actions are remembered.
    back = td.clone()
    for key in policy.state_keys:
        back[key] = other[key]
    back = policy(back)
    assert back[NOOPS_KEY].all()


def test_the_noop_memory_keeps_the_last_frames_and_forgets_the_oldest(one_object):
    env, oracle, graph = one_object
    policy = make_dorp_policy(env, oracle, graph, avoid_noops=True, noop_memory=2, **SMALL)
    rule = next(rule for rule in policy.rules if isinstance(rule, AvoidNoops))
    assert rule.memory == 2
    frames = []
    while len(frames) < 3:
        frame = env.reset()["pixels"]
        if not any(torch.equal(frame, seen) for seen in frames):
            frames.append(frame)
    state = policy.state.read(env.reset())
    active = torch.ones(1, dtype=torch.bool)

    def noop_at(frame, action):
        # the policy saw `frame`, acted `action`, and saw `frame` again
        rule.observe(state, frame, active)
        state["dorp_last_action"][0] = action
        rule.observe(state, frame, active)
        return state[NOOPS_KEY][0].nonzero().squeeze(-1).tolist()

    assert noop_at(frames[0], 1) == [1]
    assert noop_at(frames[0], 3) == [1, 3]
    assert noop_at(frames[1], 0) == [0]
    state["dorp_last_action"][0] = -1
    rule.observe(state, frames[0], active)  # frame 0 again: still remembered
    assert state[NOOPS_KEY][0].nonzero().squeeze(-1).tolist() == [1, 3]
    assert noop_at(frames[2], 2) == [2]  # a third frame takes the oldest's place
    state["dorp_last_action"][0] = -1
    rule.observe(state, frames[0], active)
    assert not state[NOOPS_KEY][0].any()
    with pytest.raises(ValueError, match="memory must be >= 1"):
        AvoidNoops(0)
