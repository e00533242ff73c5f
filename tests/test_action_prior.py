"""Action counts of code graphs and the planners' action prior: which actions changed
which one-hot in the play data, candidates drawn from per-row distributions, and the DORP
waypoint planner drawing the hop's object's actions."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from dorp_rl.data import collect_play_data
from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeGraph,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import PRIOR_KEY, make_dorp_policy
from dorp_rl.validation import MissingKeyError


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def test_graphs_count_the_actions_that_changed_each_onehot(tmp_path) -> None:
    codes = torch.tensor([[0, 0], [0, 0], [1, 0], [1, 1]])
    next_codes = torch.tensor([[1, 0], [0, 1], [1, 0], [1, 0]])
    actions = torch.tensor([2, 0, 3, 0])
    graph = CodeGraph.from_transitions(codes, next_codes, (2, 2), actions=actions, num_actions=5)
    # One-hot 0 changed once (action 2); one-hot 1 twice (action 0, both times).
    assert graph.action_counts.tolist() == [[0, 0, 1, 0, 0], [2, 0, 0, 0, 0]]
    weights = graph.action_weights(torch.tensor([[True, False], [True, True], [False, False]]))
    assert weights.tolist() == [
        [0.0, 0.0, 1.0, 0.0, 0.0],
        pytest.approx([2 / 3, 0.0, 1 / 3, 0.0, 0.0]),
        pytest.approx([0.2] * 5),  # no one-hot to change: uniform
    ]
    assert graph.action_weights(torch.tensor([[True, False]]), 6).tolist() == [[0, 0, 1, 0, 0, 0]]
    loaded = CodeGraph.load(graph.save(tmp_path / "graph.pt"))
    assert torch.equal(loaded.action_counts, graph.action_counts)
    with pytest.raises(ValueError, match="actions go up to 3, but num_actions=3"):
        CodeGraph.from_transitions(codes, next_codes, (2, 2), actions=actions, num_actions=3)
    with pytest.raises(ValueError, match="one action per transition"):
        CodeGraph.from_transitions(codes, next_codes, (2, 2), actions=actions[:3])
    bare = CodeGraph.from_transitions(codes, next_codes, (2, 2))
    assert bare.action_counts is None
    with pytest.raises(ValueError, match="no action counts"):
        bare.action_weights(torch.tensor([[True, False]]))


def test_a_graph_from_play_data_knows_which_actions_move_each_block() -> None:
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(8,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 3000, seed=0), oracle)
    counts = graph.action_counts
    assert counts.shape == (2, 8) and int(counts.sum()) > 0
    # Actions 0-3 move block 0 and only those change one-hot 0; 4-7 block 1.
    assert counts[0, :4].min() > 0 and counts[0, 4:].sum() == 0
    assert counts[1, 4:].min() > 0 and counts[1, :4].sum() == 0


def one_object_planner(kind, **kwargs):
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    planner = kind(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        planning_horizon=6,
        num_candidates=50,
        seed=0,
        action_prior_key="prior",
        **kwargs,
    )
    return env, planner


@pytest.mark.parametrize("kind", [RandomShootingPlanner, CategoricalCEMPlanner])
def test_planners_draw_their_candidates_from_each_rows_action_prior(kind) -> None:
    env, planner = one_object_planner(kind)
    assert "prior" in planner.in_keys
    td = env.reset()
    # Row 0 may only move down (action 1), row 1 only right (3): unnormalised weights.
    td["prior"] = torch.tensor([[0.0, 5.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]])
    seen = []
    evaluate = planner._evaluate

    def spy(sub, decisions):
        seen.append(decisions.clone())
        return evaluate(sub, decisions)

    planner._evaluate = spy
    out = planner(td)
    # Random shooting draws every candidate from the prior; CEM starts from it (its first
    # round of candidates), then refits to its elites.
    assert (seen[0][0] == 1).all() and (seen[0][1] == 3).all()
    if kind is RandomShootingPlanner:
        assert out["planner_plan"].tolist() == [[1] * 6, [3] * 6]


def test_a_missing_or_bad_action_prior_is_refused() -> None:
    env, planner = one_object_planner(RandomShootingPlanner)
    with pytest.raises(MissingKeyError, match="samples from 'prior'"):
        planner(env.reset())
    for bad, message in (
        (torch.tensor([[1.0, -1.0, 1.0, 1.0]] * 2), "non-negative"),
        (torch.zeros(2, 4), "positive sum"),
        (torch.ones(2, 3), "4 action weights per row, got 3"),
    ):
        with pytest.raises(ValueError, match=message):
            planner(env.reset().set("prior", bad))


def test_the_dorp_waypoint_planner_draws_the_hops_block_actions() -> None:
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(1,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 3000, seed=0), oracle)
    policy = make_dorp_policy(env, oracle, graph, num_candidates=50, seed=0)
    assert policy.action_prior_mix == 0.8  # the default for graphs with action counts
    priors = []
    planning = policy.waypoint_planner.planning

    def spy(td, *args, **kwargs):
        priors.append(td[PRIOR_KEY].clone())
        return planning(td, *args, **kwargs)

    policy.waypoint_planner.planning = spy
    # Block 0 is two regions from its goal, block 1 already at its goal.
    tasks = TensorDict(
        state=torch.tensor([[[0, 0], [12, 12]]]),
        goal_state=torch.tensor([[[0, 9], [12, 12]]]),
        batch_size=[1],
    )
    td = policy(env.reset(tasks, set_state=True))
    assert int(td["dorp_group"]) == 0
    (prior,) = priors
    # 0.8 spread over the 4 moves of block 0 as the play data saw them, 0.2 over all 8.
    assert prior[0, 4:].tolist() == pytest.approx([0.2 / 8] * 4)
    assert float(prior[0, :4].sum()) == pytest.approx(0.8 + 0.1)
    bare = CodeGraph.from_transitions(
        torch.tensor([[0, 0]]), torch.tensor([[1, 0]]), oracle.code_sizes
    )
    assert make_dorp_policy(env, oracle, bare, num_candidates=50).action_prior_mix == 0.0
    with pytest.raises(ValueError, match="needs a graph with the play data's action counts"):
        make_dorp_policy(env, oracle, bare, num_candidates=50, action_prior_mix=0.5)
