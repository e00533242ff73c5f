"""ObjectMapCost: the distance of each object map of the encoder to the goal image's.

The goal-image phase of the DORP policy adds it to the pixel distance so that every
object is pulled to its own goal place; these tests pin its formula (on frames that are
not 16 x 16), its fast path through the true dynamics, and where the policy uses it.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from dorp_rl.data import collect_play_data
from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.planners import (
    CodeGraph,
    CostSequence,
    ObjectMapCost,
    PixelDistanceCost,
    RandomShootingPlanner,
)
from dorp_rl.policies import make_dorp_policy
from dorp_rl.policies.action_priors import goal_action_prior

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PIXELS = ("next", "pixels")


def map_encoder(frame_shape=(3, 12, 10), code_sizes=(6, 6)) -> DiscreteCodeEncoder:
    torch.manual_seed(0)
    return DiscreteCodeEncoder(EncoderConfig.small(code_sizes, frame_shape=frame_shape)).eval()


def rollout_of(frames: torch.Tensor, goals: torch.Tensor) -> TensorDict:
    """A ``[B, N, H]`` rollout of ``frames`` with one goal per row."""
    b, n, h = frames.shape[:3]
    goal = goals.view(b, 1, 1, *goals.shape[1:]).expand(b, n, h, *goals.shape[1:])
    return TensorDict({"goal_pixels": goal, PIXELS: frames}, batch_size=(b, n, h))


def test_the_cost_is_the_sum_over_object_maps_of_their_distances():
    encoder = map_encoder()
    gen = torch.Generator().manual_seed(1)
    frames = torch.randint(0, 256, (2, 3, 4, 3, 12, 10), dtype=torch.uint8, generator=gen)
    goals = torch.randint(0, 256, (2, 3, 12, 10), dtype=torch.uint8, generator=gen)
    frames[1, 2, 3] = goals[1]  # one step at its goal
    frames[0, 1] = frames[0, 0]  # repeated frames are scored once, alike
    cost = ObjectMapCost(encoder)(rollout_of(frames, goals))["cost"]
    assert cost.shape == (2, 3, 4) and cost.dtype == torch.float32
    with torch.no_grad():
        maps = encoder.object_maps(frames)  # [2, 3, 4, K, 12, 10]
        goal_maps = encoder.object_maps(goals).view(2, 1, 1, *maps.shape[-3:])
    expected = (maps - goal_maps).flatten(-2).norm(dim=-1).sum(-1)
    assert torch.allclose(cost, expected, atol=1e-5)
    assert float(cost[1, 2, 3]) == 0.0 and bool((cost[0] > 0).all())
    assert torch.equal(cost[0, 1], cost[0, 0])
    # Blurred terms only add: a blurred difference is never larger than the difference.
    blurred = ObjectMapCost(encoder, blur_sigmas=(1.0, 3.0))(rollout_of(frames, goals))["cost"]
    assert bool((blurred >= cost - 1e-5).all()) and bool((blurred <= 3 * cost + 1e-5).all())
    assert float(blurred[1, 2, 3]) == 0.0


def test_each_object_pays_only_for_its_own_distance():
    """Two blocks on a 3 x 12 x 10 canvas: moving one of them leaves the other's term."""

    class ChannelMaps(torch.nn.Module):
        """Object maps read off the frame: map k is where channel k is on."""

        def object_maps(self, pixels):
            return (pixels[..., :2, :, :] > 0).to(torch.float32)

    def frame(red, green):
        out = torch.zeros(3, 12, 10, dtype=torch.uint8)
        out[0, red[0], red[1]] = 255
        out[1, green[0], green[1]] = 255
        return out

    goal = frame((2, 2), (2, 3))
    swapped = frame((2, 3), (2, 2))  # each block in the other's goal place
    aside = frame((2, 3), (3, 2))  # the green block stepped aside
    frames = torch.stack([swapped, aside]).view(1, 2, 1, 3, 12, 10)
    cost = ObjectMapCost(ChannelMaps())(rollout_of(frames, goal.unsqueeze(0)))["cost"]
    # One cell off its place costs each block sqrt(2), wherever the other block is.
    assert torch.allclose(cost.flatten(), torch.full((2,), 2 * 2**0.5))
    with pytest.raises(ValueError, match="object_maps"):
        ObjectMapCost(OracleCodeEncoder(ObjectRearrangementEnv(num_objects=1)))


def test_through_the_true_dynamics_the_fast_path_equals_the_drawn_frames():
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=0)
    td = env.reset()
    cost = CostSequence(ObjectMapCost(map_encoder((3, 16, 16)), blur_sigmas=(2.0,)))
    planner = RandomShootingPlanner(GroundTruthModelEnv(env), cost, planning_horizon=3)
    decisions = torch.randint(0, 8, (2, 16, 3), generator=torch.Generator().manual_seed(0))
    fast = cost(planner.imagine(td, decisions))["cost"]
    drawn = cost(planner.imagine(td, decisions).materialized())["cost"]
    assert torch.allclose(fast, drawn, atol=1e-5)


@pytest.mark.parametrize("make_cost", ["maps", "pixels"])
def test_pairs_scored_in_an_earlier_call_come_from_the_cache_with_the_same_costs(make_cost):
    encoder = map_encoder()
    maps_seen: list[int] = []
    object_maps = encoder.object_maps

    def counted(pixels):
        maps_seen.append(pixels.shape[0])
        return object_maps(pixels)

    encoder.object_maps = counted

    def cost_of(cache_size: int):
        if make_cost == "maps":
            return ObjectMapCost(encoder, blur_sigmas=(2.0,), cache_size=cache_size)
        return PixelDistanceCost(blur_sigmas=(2.0,), cache_size=cache_size)

    gen = torch.Generator().manual_seed(3)
    frames = torch.randint(0, 256, (2, 3, 4, 3, 12, 10), dtype=torch.uint8, generator=gen)
    goals = torch.randint(0, 256, (2, 3, 12, 10), dtype=torch.uint8, generator=gen)
    cached, plain = cost_of(2**10), cost_of(0)
    first = cached(rollout_of(frames, goals))["cost"]
    again = frames.clone()
    again[:, :, :2] = torch.randint(0, 256, again[:, :, :2].shape, dtype=torch.uint8, generator=gen)
    maps_seen.clear()
    second = cached(rollout_of(again, goals))["cost"]
    if make_cost == "maps":  # the goals' maps, then only the 12 new frames of each row
        assert maps_seen == [2, 12]
    assert torch.allclose(first, plain(rollout_of(frames, goals))["cost"], atol=1e-5)
    assert torch.allclose(second, plain(rollout_of(again, goals))["cost"], atol=1e-5)
    # A frame held for one goal is scored afresh against another goal.
    swapped = cached(rollout_of(frames, goals.flip(0)))["cost"]
    assert torch.allclose(swapped, plain(rollout_of(frames, goals.flip(0)))["cost"], atol=1e-5)
    assert not torch.allclose(swapped, first)
    if make_cost == "maps":  # new weights: nothing held is used
        with torch.no_grad():
            next(encoder.parameters()).add_(0.5)
        maps_seen.clear()
        cached(rollout_of(frames, goals))
        assert maps_seen == [2, 24]


def goal_terms(policy) -> list[type]:
    return [type(module) for module in policy.goal_planner.cost.module]


def test_the_goal_phase_adds_the_object_maps_when_the_encoder_has_them():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    play = collect_play_data(env, 500, seed=0)
    small = {"num_candidates": 16, "planning_horizon": 3}
    encoder = map_encoder((3, 16, 16), code_sizes=(8,))
    graph = CodeGraph.from_play_data(play, encoder)
    policy = make_dorp_policy(env, encoder, graph, seed=0, **small)
    assert policy.config.goal_map_weight == 4.0
    assert ObjectMapCost in goal_terms(policy) and PixelDistanceCost in goal_terms(policy)
    weights = policy.goal_planner.cost.module[-1].weights
    assert weights["goal_map_cost"] == 4.0
    off = make_dorp_policy(env, encoder, graph, seed=0, goal_map_weight=0, **small)
    assert ObjectMapCost not in goal_terms(off)
    # Oracle codes have no object maps: left to the default, the term is off; asked
    # for, it is refused by name.
    oracle = OracleCodeEncoder(env, cell_size=4)
    oracle_graph = CodeGraph.from_play_data(play, oracle)
    plain = make_dorp_policy(env, oracle, oracle_graph, seed=0, **small)
    assert plain.config.goal_map_weight == 0.0 and ObjectMapCost not in goal_terms(plain)
    with pytest.raises(ValueError, match="object_maps"):
        make_dorp_policy(env, oracle, oracle_graph, seed=0, goal_map_weight=2.0, **small)
    td = env.rollout(6, policy, break_when_any_done=False)
    assert td.batch_size == (2, 6)


def test_the_goal_planner_draws_the_actions_of_the_objects_off_their_goal_place():
    """``goal_action_prior_mix``: the goal planner samples from the play data's actions
    of the one-hots whose object maps are still off the goal image's."""
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=0)
    play = collect_play_data(env, 400, seed=0)
    encoder = map_encoder((3, 16, 16), code_sizes=(8, 8))
    graph = CodeGraph.from_play_data(play, encoder)
    # One-hot k was changed by block k's four moves only (actions 4k .. 4k + 3).
    graph.action_counts = torch.zeros(2, 8, dtype=torch.int64)
    graph.action_counts[0, :4] = graph.action_counts[1, 4:] = 10

    def block_maps(pixels):  # map k: where block k's colour is (yellow, cyan)
        red, blue = pixels[..., 0, :, :] > 0, pixels[..., 2, :, :] > 0
        return torch.stack([red & ~blue, blue & ~red], -3).float()

    encoder.object_maps = block_maps
    small = {"num_candidates": 16, "planning_horizon": 3}
    policy = make_dorp_policy(env, encoder, graph, seed=0, goal_action_prior_mix=0.8, **small)
    assert policy.goal_planner.action_prior_key == "goal_action_prior"
    goal = torch.tensor([[[2, 2], [10, 8]]])
    moved = torch.tensor([[[2, 2], [13, 2]], [[6, 9], [10, 8]]])  # block 1, then block 0 off
    pixels, goal_pixels = env.render_state(moved), env.render_state(goal).expand(2, 3, 16, 16)

    def goal_prior(pixels, goal_pixels):
        return goal_action_prior(encoder, graph, pixels, goal_pixels, 8, mix=0.8)

    prior = goal_prior(pixels, goal_pixels)
    uniform = 0.2 / 8
    expected = torch.full((2, 8), uniform)
    expected[0, 4:] += 0.8 / 4
    expected[1, :4] += 0.8 / 4
    assert torch.allclose(prior, expected)
    # Every object at its place: uniform draws.
    assert torch.allclose(goal_prior(goal_pixels, goal_pixels), torch.full((2, 8), 1 / 8))
    td = env.rollout(4, policy, break_when_any_done=False)
    assert td.batch_size == (2, 4)
    # Without object maps or action counts it is refused by name.
    oracle = OracleCodeEncoder(env, cell_size=4)
    oracle_graph = CodeGraph.from_play_data(play, oracle)
    with pytest.raises(ValueError, match="goal_action_prior_mix=0.5 needs"):
        make_dorp_policy(env, oracle, oracle_graph, goal_action_prior_mix=0.5, **small)
    # Left to the default: 0.5 with object maps and action counts, else off.
    default = make_dorp_policy(env, encoder, graph, seed=0, **small)
    assert default.config.goal_action_prior_mix == 0.5
    assert default.goal_planner.action_prior_key == "goal_action_prior"
    plain = make_dorp_policy(env, oracle, oracle_graph, seed=0, **small)
    assert plain.config.goal_action_prior_mix == 0.0
    assert plain.goal_planner.action_prior_key is None
