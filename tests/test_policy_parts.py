"""The DORP policy's parts: its config (from env profiles), its recovery rules as parts
with their own state keys, and the one state declaration behind its primer."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from dorp_rl.data import collect_play_data
from dorp_rl.envs import EnvProfile, KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import EvalSpec
from dorp_rl.planners import CodeGraph
from dorp_rl.policies import (
    AbstractGoalPolicy,
    DORPConfig,
    PolicyState,
    RecoveryRule,
    Reentry,
    StateKey,
    make_dorp_policy,
    recovery_rules,
)

SMALL = {"num_candidates": 64, "planning_horizon": 6}


@pytest.fixture(scope="module")
def one_object():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
    return env, oracle, graph


def test_the_config_comes_from_the_env_profile_and_arguments_override_it():
    assert DORPConfig.for_env("key-wall").reenter is True
    assert DORPConfig.for_env("rearrangement").waypoint_goal_weight == 0.003
    assert DORPConfig.for_env(KeyWallEnv(), reenter=False).reenter is False
    assert DORPConfig.for_env(KeyWallEnv()).replan_on_miss is True
    # A profile's settings may depend on the env's number of objects.
    counted = EnvProfile(
        name="counted",
        make_env=ObjectRearrangementEnv,
        counts_objects=True,
        env_type=ObjectRearrangementEnv,
        default_num_objects=2,
        dorp=lambda k: {"goal_patience": 10 * k},
    )
    assert DORPConfig.for_env(counted).goal_patience == 20  # the profile's default count
    # An env gives its own count: rearrangement judges a latent model's goal image on
    # decoded frames from 5 blocks on.
    assert DORPConfig.for_env(ObjectRearrangementEnv(num_objects=5)).goal_latent_weight == 0.0
    assert DORPConfig.for_env(ObjectRearrangementEnv(num_objects=3)).goal_latent_weight is None
    # A profile or its name takes a count; without one, the profile's default count.
    assert DORPConfig.for_env("rearrangement", num_objects=5).goal_latent_weight == 0.0
    assert DORPConfig.for_env("rearrangement").goal_latent_weight is None
    assert DORPConfig.for_env(counted, num_objects=3).goal_patience == 30
    # ...and the evaluation's policy of the 5-object setting gets the 5-object settings.
    assert EvalSpec("5obj", "random").dorp_config().goal_latent_weight == 0.0
    assert EvalSpec("3obj", "random").dorp_config().goal_latent_weight is None
    # The key rooms judge it on decoded frames: their agent is one pixel, which imagined
    # latents near the goal did not place.
    assert DORPConfig.for_env(KeyWallEnv()).goal_latent_weight == 0.0
    assert DORPConfig.for_env("key-corridor").goal_latent_weight == 0.0
    assert EvalSpec("keycorridor", "random").dorp_config().goal_latent_weight == 0.0
    odd = EnvProfile(name="odd", make_env=ObjectRearrangementEnv, dorp={"reentr": True})
    with pytest.raises(ValueError, match=r"env profile 'odd' name \['reentr'\]"):
        DORPConfig.for_env(odd)
    assert DORPConfig.from_dict(DORPConfig(order=(1, 0)).to_dict()).order == (1, 0)
    with pytest.raises(ValueError, match="order must be one of"):
        DORPConfig(order="random")


def test_rules_the_config_turns_off_keep_no_state(one_object):
    env, oracle, graph = one_object
    plain = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    keys = plain.make_tensordict_primer().primers.keys()
    assert "dorp_via" not in keys and "dorp_misses" in keys and "goal_code_weight" in keys
    assert not any(isinstance(rule, Reentry) for rule in plain.rules)
    both = make_dorp_policy(env, oracle, graph, seed=0, reenter=True, goal_code_weight=0, **SMALL)
    keys = both.make_tensordict_primer().primers.keys()
    assert "dorp_via" in keys and "goal_code_weight" not in keys
    # The records still name every count, 0 for a rule the policy does not have.
    td = env.rollout(3, plain, break_when_any_done=False)
    assert plain.task_records(td[:, -1])[0]["reentries"] == 0


class CountSteps(RecoveryRule):
    """A user's rule: counts the steps in which a waypoint was reached, in its own key."""

    def state_keys(self):
        return (StateKey("reached_steps", fill=0),)

    def on_reached(self, state, rows):
        state["reached_steps"][rows] += 1


def test_a_users_rule_plugs_in_with_its_own_state_key(one_object):
    env, oracle, graph = one_object
    built = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    rules = [*recovery_rules(built.config, goal_code_term=True), CountSteps()]
    policy = AbstractGoalPolicy(
        oracle, graph, built.waypoint_planner, built.goal_planner, built.config, rules=rules
    )
    assert "reached_steps" in policy.make_tensordict_primer().primers.keys()
    td = env.rollout(40, policy, break_when_any_done=False)
    counted = td["reached_steps"][:, -1, 0]
    assert int(counted.sum()) > 0
    assert torch.equal(counted, td["dorp_waypoints"][:, -1, 0])
    with pytest.raises(ValueError, match="rules must be RecoveryRule parts"):
        AbstractGoalPolicy(
            oracle, graph, built.waypoint_planner, built.goal_planner, rules=[object()]
        )


class KeepOddRowsEdges(RecoveryRule):
    """A user's rule that decides: the failed hops of odd rows keep their edge (the rule
    takes them over), and it counts them in its own key."""

    def state_keys(self):
        return (StateKey("kept_hops", fill=0),)

    def instead_of_removal(self, state, rows):
        odd = torch.arange(rows.shape[0]) % 2 == 1
        state["kept_hops"][rows & odd] += 1
        return rows & odd


def test_a_users_rule_decides_a_failed_hop_without_touching_the_loop():
    """The rule's decision is applied by the loop: the rows it takes keep their edges but
    count the removal; the others lose the edge; every row is offered in one call."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
    built = make_dorp_policy(env, oracle, graph, seed=0, **SMALL)
    rules = [KeepOddRowsEdges(), *recovery_rules(built.config, goal_code_term=True)]
    policy = AbstractGoalPolicy(
        oracle, graph, built.waypoint_planner, built.goal_planner, built.config, rules=rules
    )
    start = torch.tensor([[[0, 0]], [[0, 12]], [[12, 0]], [[12, 12]]])
    task = env.reset().set("state", start).set("goal_state", start.flip(0))
    td = policy(env.reset(task, set_state=True))
    edge = td["dorp_edge"].clone()
    assert (edge >= 0).all()  # every row is on its way to a waypoint
    td["dorp_budget"][:] = 0  # every row's waypoint missed
    td = policy(td)
    assert td["dorp_replans"].squeeze(-1).tolist() == [1, 1, 1, 1]
    assert td["kept_hops"].squeeze(-1).tolist() == [0, 1, 0, 1]
    removed = td["dorp_removed"][:, 0]
    assert torch.equal(removed[::2], edge[::2, 0]) and (removed[1::2] == -1).all()
    # make_dorp_policy takes the rule too, before the config's own
    made = make_dorp_policy(env, oracle, graph, seed=0, rules=[KeepOddRowsEdges()], **SMALL)
    assert [type(r).__name__ for r in made.rules] == [
        "KeepOddRowsEdges",
        *[type(r).__name__ for r in policy.rules[1:]],
    ]
    assert "kept_hops" in made.make_tensordict_primer().primers.keys()


def test_a_goal_cost_without_the_code_term_needs_a_zero_weight(one_object):
    env, oracle, graph = one_object
    pixels_only = make_dorp_policy(env, oracle, graph, goal_code_weight=0, **SMALL)
    with pytest.raises(ValueError, match="does not read 'goal_code_weight'"):
        AbstractGoalPolicy(oracle, graph, pixels_only.waypoint_planner, pixels_only.goal_planner)
    with pytest.raises(ValueError, match="unknown|not accepted|accepts"):
        AbstractGoalPolicy(
            oracle,
            graph,
            pixels_only.waypoint_planner,
            pixels_only.goal_planner,
            num_candidates=5,  # a planner's setting: the planners are built already
        )


def test_the_state_declaration_gives_primer_fills_and_shape_errors():
    state = PolicyState([StateKey("edge", fill=-1), StateKey("mask", torch.bool, width=3)])
    with pytest.raises(ValueError, match="declared twice"):
        PolicyState([StateKey("edge"), StateKey("edge")])
    primer = state.primer()
    assert set(primer.primers.keys()) == {"edge", "mask"}
    values = state.read(TensorDict({"edge": torch.tensor([[4], [7]])}, [2]))
    assert values["edge"].tolist() == [[4], [7]] and values["mask"].dtype is torch.bool
    state.restart(values, torch.tensor([True, False]))
    assert values["edge"].tolist() == [[-1], [7]]
    with pytest.raises(ValueError, match=r"'mask' must have shape \[2, 3\]"):
        state.read(TensorDict({"mask": torch.zeros(2, 4, dtype=torch.bool)}, [2]))


def test_every_registered_profile_names_only_dorp_config_fields():
    from dorp_rl.envs import env_profile, registered_profiles

    names = registered_profiles()
    assert len(names) >= 3
    for name in names:
        profile = env_profile(name)
        config = DORPConfig.for_env(profile)
        for key, value in profile.dorp_overrides().items():
            assert getattr(config, key) == value
