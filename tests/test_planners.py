"""Tests of the discrete MPC planners, the rollout costs and the visual-foresight policy.

Small candidate counts and horizons throughout: each planning call is a few
milliseconds on the ground-truth model.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import TensorDictPrimer

from dorp_rl.envs import ObjectRearrangementEnv
from dorp_rl.envs.planning import GroundTruthModelEnv, VideoModelEnv
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeMatchCost,
    DiscreteMPCPlanner,
    FirstArrival,
    MissingRolloutKeyError,
    NegativeRewardCost,
    PixelDistanceCost,
    RandomShootingPlanner,
    RolloutCost,
    WeightedCostSum,
    aggregate_steps,
    improves,
    select_best,
)
from dorp_rl.policies import VisualForesightPolicy

PLANNERS = {
    "rs": RandomShootingPlanner,
    # The elites are the top 10 % of the candidates (num_candidates=64 -> top_k=6).
    "cem": lambda *a, **k: CategoricalCEMPlanner(
        *a, top_k=max(1, round(0.1 * k["num_candidates"])), **k
    ),
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


class FirstActionCost(RolloutCost):
    """0 only when the first action is ``target``: a toy cost with one right answer."""

    def __init__(self, target: int = 3) -> None:
        super().__init__(step_aggregation="sum")
        self.target = target
        self.in_keys = ["action"]

    def per_step_cost(self, rollout):
        action = rollout["action"].squeeze(-1)  # [B, N, H]
        cost = torch.zeros(action.shape, dtype=torch.float32)
        cost[..., 0] = (action[..., 0] != self.target).float()
        return cost


class DecodingModel:
    """A perfect 'video model' of 1-object rearrangement: reads the block, moves it, redraws."""

    def __init__(self, env: ObjectRearrangementEnv) -> None:
        self.env = env

    def predict(self, pixels, action, deterministic=True):
        occupied = pixels.amax(1) > 0  # [N, 16, 16]
        rows = occupied.any(-1).to(torch.int64).argmax(-1)
        cols = occupied.any(-2).to(torch.int64).argmax(-1)
        state = torch.stack([rows, cols], -1).unsqueeze(-2)  # [N, 1, 2]
        return self.env.render_state(self.env.transition(state, action.squeeze(-1)))


def two_object_env(batch: int = 3, seed: int = 0) -> ObjectRearrangementEnv:
    return ObjectRearrangementEnv(num_objects=2, batch_size=(batch,), seed=seed)


def tasks(env: ObjectRearrangementEnv, states, goals) -> TensorDict:
    """Resets ``env`` to given start and goal configurations."""
    td = TensorDict(
        state=torch.tensor(states), goal_state=torch.tensor(goals), batch_size=(len(states),)
    )
    return env.reset(td, set_state=True)


# --------------------------------------------------------------------------- #
# Costs
# --------------------------------------------------------------------------- #
def test_pixel_distance_cost_values():
    goal = torch.zeros(1, 3, 16, 16, dtype=torch.uint8)
    frames = torch.zeros(1, 2, 3, 3, 16, 16, dtype=torch.uint8)
    frames[0, 0, 1, 0, 4, 4] = 255  # one channel of one pixel fully on
    frames[0, 1, 2] = 255  # the whole frame white
    rollout = TensorDict(
        {
            "goal_pixels": goal.view(1, 1, 1, 3, 16, 16).expand(1, 2, 3, 3, 16, 16),
            ("next", "pixels"): frames,
        },
        batch_size=(1, 2, 3),
    )
    cost = PixelDistanceCost()(rollout)["cost"]
    assert cost.shape == (1, 2, 3) and cost.dtype == torch.float32
    expected = torch.tensor([[[0.0, 1.0, 0.0], [0.0, 0.0, 768**0.5]]])
    assert torch.allclose(cost, expected)
    with pytest.raises(MissingRolloutKeyError, match="goal_pixels"):
        PixelDistanceCost()(rollout.exclude("goal_pixels"))


def test_pixel_distance_cost_with_one_goal_per_row_in_small_chunks():
    gen = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 256, (3, 4, 5, 3, 16, 16), dtype=torch.uint8, generator=gen)
    goals = torch.randint(0, 256, (3, 3, 16, 16), dtype=torch.uint8, generator=gen)
    rollout = TensorDict(
        {
            "goal_pixels": goals.view(3, 1, 1, 3, 16, 16).expand(3, 4, 5, 3, 16, 16),
            ("next", "pixels"): frames,
        },
        batch_size=(3, 4, 5),
    )
    naive = (frames.double() - goals.view(3, 1, 1, 3, 16, 16).double()) / 255
    expected = naive.square().flatten(-3).sum(-1).sqrt().float()
    for chunk_size in (7, 512):
        cost = PixelDistanceCost(chunk_size=chunk_size)(rollout)["cost"]
        assert torch.allclose(cost, expected, atol=1e-4)


class CornerEncoder(nn.Module):
    """Fake 2-one-hot encoder: one-hot i reads channel i of pixel (0, 0) (code = value // 64)."""

    def forward(self, pixels):
        values = pixels[..., :2, 0, 0].to(torch.int64) // 64  # [*B, 2] in 0..3
        probs = torch.nn.functional.one_hot(values, 4).float() * 0.9 + 0.025
        return values, probs


def code_rollout(start: tuple[int, int], steps: list[tuple[int, int]], target, mask=None):
    """A [1, 1, H] rollout whose frames carry the given codes in pixel (0, 0)."""

    def frame(code):
        f = torch.zeros(3, 16, 16, dtype=torch.uint8)
        f[0, 0, 0], f[1, 0, 0] = code[0] * 64, code[1] * 64
        return f

    h = len(steps)
    data = {
        "pixels": frame(start).expand(1, 1, h, 3, 16, 16),
        "subgoal_code": torch.tensor(target).expand(1, 1, h, 2),
        ("next", "pixels"): torch.stack([frame(c) for c in steps]).view(1, 1, h, 3, 16, 16),
    }
    if mask is not None:
        data["subgoal_onehots"] = torch.tensor(mask).expand(1, 1, h, 2)
    return TensorDict(data, batch_size=(1, 1, h))


def test_code_match_cost_on_chosen_onehots():
    # Start (0, 0); target code 2 on one-hot 0; one-hot 1 must stay at 0.
    rollout = code_rollout((0, 0), [(1, 0), (2, 1), (2, 0), (2, 0)], target=(2, 3))
    cost = CodeMatchCost(CornerEncoder(), onehots=[0], step_penalty=0.0)(rollout)["cost"][0, 0]
    # Per step: (1 on a miss, 0 on a match) - tie_break (1e-3) x the mean probability of
    # the wanted codes (CornerEncoder: 0.925 on its code, 0.025 on the others).
    # Not there / the other one-hot changed: one wanted code of two has its 0.925.
    assert cost[0].item() == pytest.approx(1 - 1e-3 * 0.475)
    assert cost[1].item() == pytest.approx(1 - 1e-3 * 0.475)
    # A match, both wanted codes at 0.925.
    assert cost[2].item() == pytest.approx(-1e-3 * 0.925) and cost[3] == cost[2]
    # With a step penalty the earlier of two matching steps is the cheaper, by more
    # than any confidence difference; misses are not penalised.
    cost = CodeMatchCost(CornerEncoder(), onehots=[0], step_penalty=2e-3)(rollout)["cost"][0, 0]
    assert cost[2] < cost[3] - 1e-3 and cost[3] < 0.1
    assert cost[0] > 0.99 and torch.isclose(cost[0], cost[1])
    with pytest.raises(ValueError, match="step_penalty"):
        CodeMatchCost(CornerEncoder(), step_penalty=0.5)
    # All one-hots (onehots=None): (2, 3) is never reached.
    assert (CodeMatchCost(CornerEncoder())(rollout)["cost"] > 0.99).all()
    # Per-row choice through a mask key: one-hot 1 only.
    rollout = code_rollout((0, 0), [(0, 3), (1, 3)], target=(2, 3), mask=(False, True))
    cost = CodeMatchCost(CornerEncoder(), onehots="subgoal_onehots")(rollout)["cost"][0, 0]
    assert cost[0] < 0.01 and cost[1] > 0.99
    with pytest.raises(MissingRolloutKeyError, match="subgoal_code"):
        CodeMatchCost(CornerEncoder())(rollout.exclude("subgoal_code"))


def test_first_arrival_judges_a_plan_where_it_first_reaches_its_target():
    # Two candidates, both reaching the code at step 1; the first gets cheaper later
    # (step 3), which a policy that stops at the first arrival never executes.
    code = torch.tensor([[[1.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0]]])
    total = torch.tensor([[[1.3, 0.08, 1.2, 0.01], [1.3, 0.05, 0.06, 0.07]]])
    rollout = TensorDict({"code": code, "total": total}, batch_size=(1, 2, 4))
    plain, step = aggregate_steps(total[0], "min")
    assert plain.argmin() == 0 and step.tolist() == [3, 1]  # the later step wins
    cut = FirstArrival("code", cost_key="total", out_key="cost")(rollout)["cost"][0]
    assert torch.isinf(cut[:, 2:]).all() and torch.equal(cut[:, :2], total[0, :, :2])
    score, step = aggregate_steps(cut, "min")
    assert score.argmin() == 1 and step.tolist() == [1, 1]  # judged at arrival
    # A candidate that never arrives keeps every step.
    never = TensorDict(
        {"code": torch.ones(1, 1, 3), "total": torch.tensor([[[1.2, 1.1, 1.3]]])},
        batch_size=(1, 1, 3),
    )
    assert torch.equal(FirstArrival("code", cost_key="total")(never)["total"], never["total"])
    with pytest.raises(MissingRolloutKeyError, match="'code'"):
        FirstArrival("code", cost_key="total")(never.exclude("code"))


class FixedPlan(DiscreteMPCPlanner):
    """One candidate per row: the given decisions."""

    def __init__(self, *args, plan, **kwargs):
        super().__init__(*args, num_candidates=1, **kwargs)
        self.fixed = torch.tensor(plan)

    def _optimize(self, td, previous_plan, shift, valid):
        decisions = self.fixed.expand(td.shape[0], 1, -1).clone()
        score, step = self._evaluate(td, decisions)
        return decisions[:, 0], score[:, 0], step[:, 0]


def test_pruning_drops_a_detour_and_draws_no_random_numbers():
    # One block goes right, back left, then right twice: it reaches the goal (two cells
    # right) at step 3. Dropping the detour reaches it at step 1.
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    right, left = 3, 2
    td = tasks(env, [[[6, 6]]], [[[6, 8]]])
    plan = [right, left, right, right, left, left]
    planners = {
        prune: FixedPlan(
            GroundTruthModelEnv(env),
            PixelDistanceCost(),
            planning_horizon=6,
            execution="open_loop",
            plan=plan,
            prune=prune,
            seed=0,
        )
        for prune in (False, True)
    }
    kept = planners[False](td.clone())
    pruned = planners[True](td.clone())
    assert kept["planner_plan"].tolist() == [plan] and kept["planner_length"].item() == 4
    # drop 1 wins (drop 0 or 3 never reach the goal); the last action fills the horizon
    assert pruned["planner_plan"].tolist() == [[right, right, right, left, left, left]]
    assert pruned["planner_length"].item() == 2
    assert pruned["planner_cost"].item() == kept["planner_cost"].item() == 0.0
    # the pruned plan really arrives where it stops
    state = env.transition(td["state"], torch.tensor([right]))
    state = env.transition(state, torch.tensor([right]))
    assert torch.equal(state, td["goal_state"])
    generators = [p.generator.get_state() for p in planners.values()]
    assert torch.equal(*generators)
    # a best step at 0 has nothing to drop
    first = FixedPlan(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        planning_horizon=6,
        plan=[right] * 6,
        prune=True,
    )
    one = tasks(env, [[[6, 6]]], [[[6, 7]]])
    assert first(one)["planner_plan"].tolist() == [[right] * 6]
    with pytest.raises(ValueError, match="prune must be True or False"):
        FixedPlan(GroundTruthModelEnv(env), PixelDistanceCost(), plan=[0] * 14, prune=1)


def test_improves_prefers_lower_then_earlier():
    score, step = torch.tensor([1.0, 1.0, 2.0, 0.5]), torch.tensor([3, 1, 0, 9])
    best_score, best_step = torch.tensor(1.0), torch.tensor(2)
    assert improves(score, step, best_score, best_step).tolist() == [False, True, False, True]


def test_code_match_cost_prefers_confident_matches():
    class Confidence(CornerEncoder):
        def forward(self, pixels):
            values, probs = super().forward(pixels)
            boost = pixels[..., 2, 0, 0].float() / 255  # channel 2 raises the confidence
            probs = probs * (1 - boost[..., None, None]) + boost[..., None, None] * (
                torch.nn.functional.one_hot(values, 4).float()
            )
            return values, probs

    rollout = code_rollout((0, 0), [(1, 0), (1, 0)], target=(1, 0))
    rollout["next", "pixels"][0, 0, 1, 2, 0, 0] = 255
    cost = CodeMatchCost(Confidence(), step_penalty=0.0)(rollout)["cost"][0, 0]
    assert cost[1] < cost[0] <= 0


def test_weighted_cost_sum_and_step_aggregations():
    rollout = code_rollout((0, 0), [(1, 0), (2, 0)], target=(2, 0))
    rollout["goal_pixels"] = rollout["next", "pixels"][:, :, 1:].expand(1, 1, 2, 3, 16, 16)
    a = CodeMatchCost(CornerEncoder(), out_key="code_cost")
    b = PixelDistanceCost(out_key="pixel_cost")
    total = TensorDictSequential(a, b, WeightedCostSum({"code_cost": 2.0, "pixel_cost": 0.5}))
    out = total(rollout.clone())
    expected = 2 * a(rollout.clone())["code_cost"] + 0.5 * b(rollout.clone())["pixel_cost"]
    assert torch.allclose(out["cost"], expected)
    assert (a.step_aggregation, b.step_aggregation) == ("min", "min")
    assert WeightedCostSum({"code_cost": 1.0}).step_aggregation == "sum"
    assert NegativeRewardCost().step_aggregation == "sum"
    assert set(total.in_keys) >= {("next", "pixels"), "goal_pixels", "subgoal_code"}
    assert "code_cost" not in total.in_keys and total.out_keys[-1] == "cost"
    with pytest.raises(MissingRolloutKeyError, match="pixel_cost"):
        WeightedCostSum({"pixel_cost": 1.0})(rollout.clone())
    per_step = torch.tensor([[3.0, 1.0, 1.0, 2.0], [0.0, 5.0, 0.0, 0.0]])
    assert aggregate_steps(per_step, "min")[0].tolist() == [1.0, 0.0]
    assert aggregate_steps(per_step, "min")[1].tolist() == [1, 0]
    assert aggregate_steps(per_step, "sum")[0].tolist() == [7.0, 5.0]
    assert aggregate_steps(per_step, "final")[0].tolist() == [2.0, 0.0]
    with pytest.raises(ValueError, match="step_aggregation"):
        aggregate_steps(per_step, "mean")
    with pytest.raises(ValueError, match="step_aggregation"):
        PixelDistanceCost(step_aggregation="mean")
    # Equal scores: the earliest step wins.
    assert select_best(torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([[0, 5, 2]])).item() == 2


# --------------------------------------------------------------------------- #
# Planners
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_planner_finds_the_best_action_of_a_toy_cost(name):
    env = two_object_env()
    planner = PLANNERS[name](
        GroundTruthModelEnv(env), FirstActionCost(3), num_candidates=64, planning_horizon=4, seed=0
    )
    td = planner(env.reset())
    assert td["action"].shape == (3, 1) and (td["action"] == 3).all()
    assert (td["planner_cost"] == 0).all() and (td["planner_plan"][:, 0] == 3).all()


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_actions_respect_the_spec(name):
    env = two_object_env(batch=2)
    planner = PLANNERS[name](
        GroundTruthModelEnv(env), PixelDistanceCost(), num_candidates=32, planning_horizon=4, seed=1
    )
    td = env.rollout(5, planner, break_when_any_done=False)
    assert td["action"].dtype == torch.int64 and td["action"].shape == (2, 5, 1)
    assert env.action_spec.is_in(td["action"][:, 0])
    assert ((td["action"] >= 0) & (td["action"] < env.num_actions)).all()
    assert td["planner_plan"].shape == (2, 5, 4)


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_rows_do_not_influence_each_other(name):
    env = two_object_env(batch=3)
    model = GroundTruthModelEnv(env)
    states = [[[0, 0], [6, 6]], [[10, 2], [3, 9]], [[12, 12], [0, 8]]]
    goals = [[[1, 2], [6, 6]], [[10, 4], [3, 9]], [[12, 10], [2, 8]]]
    td = tasks(env, states, goals)

    def plan(batch):
        planner = PLANNERS[name](
            model, PixelDistanceCost(), num_candidates=64, planning_horizon=6, seed=7
        )
        return planner(batch.clone())["planner_plan"]

    together = plan(td)
    alone = plan(td[:1])
    assert torch.equal(alone[0], together[0])
    other_goal = td.clone()
    other_goal["goal_pixels"][1] = other_goal["goal_pixels"][2]
    changed = plan(other_goal)
    assert torch.equal(changed[0], together[0]) and torch.equal(changed[2], together[2])
    assert not torch.equal(changed[1], together[1])  # the change did matter to row 1


@pytest.mark.parametrize("name", sorted(PLANNERS))
def test_same_seed_same_plan(name):
    env = two_object_env()
    td = env.reset()
    model = GroundTruthModelEnv(env)

    def make(seed):
        return PLANNERS[name](
            model, PixelDistanceCost(), num_candidates=32, planning_horizon=6, seed=seed
        )

    first, second = make(11), make(11)
    a, b = first(td.clone()), second(td.clone())
    assert torch.equal(a["planner_plan"], b["planner_plan"])
    again = first(td.clone())  # the generator moved on...
    first.set_seed(11)  # ...and set_seed rewinds it
    assert torch.equal(first(td.clone())["planner_plan"], a["planner_plan"])
    assert again["planner_plan"].shape == a["planner_plan"].shape


def test_cem_warm_start_shifts_the_plan():
    env = two_object_env()
    td = env.reset()
    # With warm_start_mix=1 and one iteration every candidate is the shifted plan.
    planner = CategoricalCEMPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(step_aggregation="sum"),
        num_candidates=16,
        planning_horizon=6,
        optim_steps=1,
        top_k=1,
        warm_start_mix=1.0,
        seed=0,
    )
    first = planner(td.clone())
    plan = first["planner_plan"].clone()
    assert (first["planner_cursor"] == 1).all()
    second = planner(first.clone())
    assert torch.equal(second["planner_plan"][:, :-1], plan[:, 1:])
    assert torch.equal(second["planner_plan"][:, -1], plan[:, -1])  # padded with the last action
    assert torch.equal(second["action"].squeeze(-1), plan[:, 1])
    # A new episode (is_init) or warm_start=False drops the previous plan.
    restarted = first.clone()
    restarted["is_init"] = torch.ones(3, 1, dtype=torch.bool)
    fresh = planner(restarted)["planner_plan"]
    assert not torch.equal(fresh[:, :-1], plan[:, 1:])
    probs = planner.initial_probs(
        plan, torch.ones(3, dtype=torch.int64), torch.zeros(3, dtype=torch.bool)
    )
    assert torch.allclose(probs, torch.full_like(probs, 1 / 8))


def test_cem_initial_probs_with_action_repeat():
    env = two_object_env()
    planner = CategoricalCEMPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        num_candidates=8,
        planning_horizon=6,
        action_repeat=2,
        top_k=1,
        warm_start_mix=0.5,
        seed=0,
    )
    plan = torch.tensor([[0, 0, 1, 1, 2, 2]])
    probs = planner.initial_probs(plan, torch.tensor([2]), torch.tensor([True]))
    assert probs.shape == (1, 3, 8)
    assert probs[0].argmax(-1).tolist() == [1, 2, 2]  # shifted by one decision, padded
    assert torch.allclose(probs.sum(-1), torch.ones(1, 3))
    assert torch.isclose(probs[0, 0, 1], torch.tensor(0.5 + 0.5 / 8))
    refit = planner._refit(probs, torch.zeros(1, 4, 3, dtype=torch.int64))
    assert (refit > 0).all() and torch.allclose(refit.sum(-1), torch.ones(1, 3))


def test_action_repeat_repeats_decisions():
    env = two_object_env()
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        num_candidates=16,
        planning_horizon=8,
        action_repeat=2,
    )
    plan = planner(env.reset())["planner_plan"]
    assert torch.equal(plan[:, 0::2], plan[:, 1::2])


def _sampled_candidates(planner, td):
    """The candidate decisions ``[B, N, H]`` of one planning call."""
    seen = []
    evaluate = planner._evaluate

    def capture(rows, decisions):
        seen.append(decisions.clone())
        return evaluate(rows, decisions)

    planner._evaluate = capture
    planner(td)
    return seen[0]


def test_action_persistence_draws_runs_of_one_action():
    env = two_object_env()
    make = lambda p: RandomShootingPlanner(  # noqa: E731
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        num_candidates=400,
        planning_horizon=10,
        action_persistence=p,
        seed=0,
    )
    td = env.reset()
    independent = _sampled_candidates(make(0.0), td.clone())
    sticky = _sampled_candidates(make(0.8), td.clone())
    same = lambda d: (d[..., 1:] == d[..., :-1]).float().mean().item()  # noqa: E731
    # Independent uniform draws over 8 actions repeat 1/8 of the time; with persistence p
    # a decision repeats with probability p + (1 - p) / 8.
    assert abs(same(independent) - 1 / 8) < 0.02
    assert abs(same(sticky) - (0.8 + 0.2 / 8)) < 0.02
    # Every action still starts sequences, and the default draws what it always drew.
    assert set(sticky[..., 0].unique().tolist()) == set(range(8))
    baseline = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        num_candidates=400,
        planning_horizon=10,
        seed=0,
    )
    assert torch.equal(_sampled_candidates(baseline, td.clone()), independent)


@pytest.mark.parametrize("bad", [-0.1, 1.0, 2])
def test_action_persistence_out_of_range(bad):
    env = two_object_env()
    with pytest.raises(ValueError, match="action_persistence must be in"):
        RandomShootingPlanner(GroundTruthModelEnv(env), PixelDistanceCost(), action_persistence=bad)


def test_open_loop_emits_the_stored_sequence_then_replans():
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(2,), seed=3, terminate_on_success=False)
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(step_aggregation="sum"),
        num_candidates=16,
        planning_horizon=4,
        execution="open_loop",
        seed=0,
    )
    td = env.rollout(6, planner, break_when_any_done=False)
    plan = td["planner_plan"][:, 0]
    assert torch.equal(td["action"][:, :4, 0], plan)
    assert torch.equal(td["planner_plan"][:, :4], plan.unsqueeze(1).expand(2, 4, 4))
    assert td["planner_cursor"][0, :, 0].tolist() == [1, 2, 3, 4, 1, 2]
    assert (td["planner_length"] == 4).all()
    # "min" keeps only the prefix up to the best step.
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(step_aggregation="min"),
        num_candidates=16,
        planning_horizon=4,
        execution="open_loop",
        seed=0,
    )
    out = planner(env.reset())
    assert ((out["planner_length"] >= 1) & (out["planner_length"] <= 4)).all()


def test_unbatched_acting_env():
    env = ObjectRearrangementEnv(num_objects=1, seed=0)
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), num_candidates=16, planning_horizon=4, seed=0
    )
    td = env.rollout(3, planner)
    assert td["action"].shape[1:] == (1,) and td["planner_plan"].shape[1:] == (4,)


def test_same_cost_and_plan_through_a_world_model():
    """A perfect frame predictor gives the ground-truth model's plan (same seed)."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    td = env.reset()
    truth = CategoricalCEMPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        planning_horizon=5,
        num_candidates=32,
        seed=3,
        top_k=1,
    )
    learned = CategoricalCEMPlanner(
        VideoModelEnv(DecodingModel(env), num_actions=4),
        PixelDistanceCost(),
        planning_horizon=5,
        num_candidates=32,
        seed=3,
        top_k=1,
    )
    assert torch.equal(truth(td.clone())["planner_plan"], learned(td.clone())["planner_plan"])


def test_code_match_cost_drives_a_planner_to_the_subgoal():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    td = tasks(env, [[[0, 1]]], [[[8, 8]]])
    # CornerEncoder reads pixel (0, 0): yellow there (block moved left) is code (3, 3).
    td["subgoal_code"] = torch.tensor([[3, 3]])
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        CodeMatchCost(CornerEncoder()),
        num_candidates=64,
        planning_horizon=4,
        execution="open_loop",
        seed=0,
    )
    out = planner(td)
    assert out["action"].item() == 2  # left
    assert out["planner_cost"].item() < 0.5 and out["planner_length"].item() == 1  # a match


def test_code_match_cost_with_the_real_encoder_runs_in_a_planner():
    from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig

    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8))).train()
    env = two_object_env(batch=2)
    td = env.reset()
    td["subgoal_code"] = torch.zeros(2, 2, dtype=torch.int64)
    planner = CategoricalCEMPlanner(
        GroundTruthModelEnv(env),
        CodeMatchCost(encoder, onehots=[1]),
        num_candidates=16,
        planning_horizon=4,
        action_repeat=2,
        top_k=4,
        seed=0,
    )
    out = planner(td.clone())
    plan = out["planner_plan"]  # [2, 4] env steps: two decisions, each repeated twice
    assert torch.equal(plan[:, 0::2], plan[:, 1::2]) and torch.equal(out["action"], plan[:, :1])
    # The reported cost is the cost of the plan's own frames (the best of its steps),
    # rolled out here with the true dynamics.
    states, frames = td["state"], []
    for t in range(4):
        states = env.transition(states, plan[:, t])
        frames.append(env.render_state(states))
    rollout = TensorDict(
        {
            "pixels": td["pixels"][:, None, None].expand(2, 1, 4, 3, 16, 16),
            "subgoal_code": td["subgoal_code"][:, None, None].expand(2, 1, 4, 2),
            ("next", "pixels"): torch.stack(frames, 1)[:, None],
        },
        batch_size=(2, 1, 4),
    )
    own = CodeMatchCost(encoder, onehots=[1])(rollout)["cost"][:, 0]
    assert torch.allclose(out["planner_cost"][:, 0], own.min(-1).values)
    assert encoder.training  # the cost restores the encoder's mode


def test_errors():
    env = two_object_env()
    model = GroundTruthModelEnv(env)
    cost = PixelDistanceCost()
    with pytest.raises(ValueError, match="batch-locked"):
        RandomShootingPlanner(env, cost)
    with pytest.raises(ValueError, match="horizon"):
        RandomShootingPlanner(model, cost, planning_horizon=0)
    with pytest.raises(ValueError, match="num_candidates"):
        CategoricalCEMPlanner(model, cost, num_candidates=0)
    with pytest.raises(ValueError, match="action_repeat must divide planning_horizon"):
        RandomShootingPlanner(model, cost, planning_horizon=7, action_repeat=2)
    for top_k in (0, 1001, 2.5):
        with pytest.raises(ValueError, match="top_k"):
            CategoricalCEMPlanner(model, cost, top_k=top_k)
    with pytest.raises(ValueError, match="top_k"):
        CategoricalCEMPlanner(model, cost, num_candidates=16)  # default top_k=20 > 16
    for steps in (0, 1.5):
        with pytest.raises(ValueError, match="optim_steps"):
            CategoricalCEMPlanner(model, cost, optim_steps=steps)
    with pytest.raises(ValueError, match="step_aggregation"):
        RandomShootingPlanner(model, cost, step_aggregation="mean")
    with pytest.raises(ValueError, match="cost_key"):
        RandomShootingPlanner(model, cost, cost_key="pixel_cost")
    with pytest.raises(ValueError, match="execution"):
        RandomShootingPlanner(model, cost, execution="closed")
    with pytest.raises(ValueError, match="depth"):
        RandomShootingPlanner(model, PixelDistanceCost(pixels_key=("next", "depth")))
    planner = RandomShootingPlanner(model, cost, num_candidates=8, planning_horizon=3)
    with pytest.raises(ValueError, match="goal_pixels") as info:
        planner(env.reset().exclude("goal_pixels"))
    assert isinstance(info.value, MissingRolloutKeyError)

    class WrongShape(FirstActionCost):
        def per_step_cost(self, rollout):
            return super().per_step_cost(rollout).unsqueeze(-1)  # [B, N, H, 1]

    with pytest.raises(ValueError, match=r"per-step cost of shape \[3, 8, 3\]"):
        RandomShootingPlanner(model, WrongShape(), num_candidates=8, planning_horizon=3)(
            env.reset()
        )

    class WritesNothing(FirstActionCost):
        def forward(self, rollout):  # declares "cost" but never writes it
            return rollout

    with pytest.raises(ValueError, match="'cost'"):
        RandomShootingPlanner(model, WritesNothing(), num_candidates=8, planning_horizon=3)(
            env.reset()
        )


def test_composed_cost_plans_like_its_single_term():
    """A TensorDictSequential of costs plugs into a planner through its in/out keys."""
    env = two_object_env()
    td = env.reset()
    model = GroundTruthModelEnv(env)
    composed = TensorDictSequential(
        PixelDistanceCost(out_key="pixel_cost"),
        WeightedCostSum({"pixel_cost": 2.0}, out_key="total"),
    )
    planner = RandomShootingPlanner(
        model, composed, planning_horizon=4, num_candidates=16, step_aggregation="min", seed=0
    )
    assert planner.cost_key == "total" and planner.step_aggregation == "min"
    assert "goal_pixels" in planner.in_keys and "pixel_cost" not in planner.in_keys
    single = RandomShootingPlanner(
        model, PixelDistanceCost(), planning_horizon=4, num_candidates=16, seed=0
    )
    a, b = planner(td.clone()), single(td.clone())
    assert torch.equal(a["planner_plan"], b["planner_plan"])
    assert torch.allclose(a["planner_cost"], 2 * b["planner_cost"])
    # Without step_aggregation the planner takes the cost's, and a sequence has none: "sum".
    assert RandomShootingPlanner(model, composed).step_aggregation == "sum"
    explicit = RandomShootingPlanner(model, composed, cost_key="pixel_cost")
    assert explicit.cost_key == "pixel_cost"


def test_make_primer():
    env = two_object_env(batch=2)
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), num_candidates=8, planning_horizon=5
    )
    primer = planner.make_primer()
    assert isinstance(primer, TensorDictPrimer)
    assert set(primer.primers.keys()) == set(planner.state_keys)
    primed = env.append_transform(primer)
    td = primed.reset()
    assert td["planner_plan"].shape == (2, 5) and (td["planner_length"] == 0).all()


# --------------------------------------------------------------------------- #
# Visual foresight
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("variant", ["cem", "rs"])
def test_visual_foresight_reaches_nearby_goals(variant):
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
    states = [[[5, 5]], [[2, 2]], [[10, 3]], [[0, 12]]]
    goals = [[[5, 8]], [[4, 3]], [[8, 5]], [[3, 12]]]
    td = tasks(env, states, goals)
    top_k = {"top_k": 4} if variant == "cem" else {}  # the paper's top 2 % of 200
    policy = VisualForesightPolicy(
        GroundTruthModelEnv(env), variant, planning_horizon=8, num_candidates=200, seed=0, **top_k
    )
    out = env.rollout(
        16,
        policy,
        tensordict=td,
        auto_reset=False,
        break_when_any_done=False,
        break_when_all_done=True,
    )
    assert out["next", "success"].any(1).all()


def test_visual_foresight_in_a_collector():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
    policy = VisualForesightPolicy(
        GroundTruthModelEnv(env), "rs", num_candidates=32, planning_horizon=4, seed=0
    )
    collector = Collector(
        env, policy, frames_per_batch=8, total_frames=16, auto_register_policy_transforms=True
    )
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch["action"].shape == (2, 4, 1)
        assert ((batch["action"] >= 0) & (batch["action"] < 4)).all()
        cursor, length = batch["planner_cursor"][..., 0], batch["planner_length"][..., 0]
        assert ((cursor >= 1) & (cursor <= length)).all()
    with pytest.raises(ValueError, match="variant"):
        VisualForesightPolicy(GroundTruthModelEnv(env), "mppi")
    literal = VisualForesightPolicy(
        GroundTruthModelEnv(env),
        "rs",
        step_aggregation="final",
        planning_horizon=4,
        num_candidates=16,
        seed=0,
    )
    assert literal.planner.execution == "open_loop"
    assert literal.planner.step_aggregation == "final"
    assert (literal(env.reset())["planner_length"] == 4).all()  # the whole sequence
    cem = VisualForesightPolicy(GroundTruthModelEnv(env), "cem").planner
    assert (cem.num_candidates, cem.top_k, cem.optim_steps) == (1000, 20, 3)
    assert cem.planning_horizon == 14


def test_finished_rows_are_not_planned_for():
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(3,), seed=0)
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        PixelDistanceCost(),
        num_candidates=64,
        planning_horizon=6,
        execution="open_loop",
        seed=0,
    )
    planned: list[int] = []
    plan = planner._plan

    def counting(td, *args):
        planned.append(td.batch_size[0])
        return plan(td, *args)

    planner._plan = counting
    td = env.reset()
    td["done"][1] = True
    planner(td)
    assert planned == [2] and td["planner_length"][1] == 0
    # In a batched rollout, rows that are done stop costing planning calls.
    planned.clear()
    rollout = env.rollout(
        200,
        planner,
        tensordict=env.reset(),
        break_when_any_done=False,
        break_when_all_done=True,
        auto_reset=False,
    )
    done = rollout["next", "done"].squeeze(-1)
    assert done.any(-1).all()
    steps_until_done = done.float().argmax(-1) + 1
    assert sum(planned) <= int(steps_until_done.sum())


def test_blurred_pixel_distance_sees_blocks_that_do_not_overlap_their_goal():
    env = ObjectRearrangementEnv(num_objects=1, seed=0)
    goal = env.render_state(torch.tensor([[2, 2]]))
    frames = env.render_state(torch.tensor([[[8, 2]], [[6, 2]], [[4, 2]]]))  # 6, 4, 2 rows away
    rollout = TensorDict(
        {
            "goal_pixels": goal.view(1, 1, 1, 3, 16, 16).expand(1, 1, 3, 3, 16, 16),
            ("next", "pixels"): frames.view(1, 1, 3, 3, 16, 16),
        },
        batch_size=(1, 1, 3),
    )
    plain = PixelDistanceCost()(rollout.clone())["cost"].flatten()
    blurred = PixelDistanceCost(blur_sigmas=(1.0, 2.0, 4.0))(rollout)["cost"].flatten()
    assert torch.allclose(plain, plain[0].expand(3))  # flat: no overlap, same distance
    assert blurred[0] > blurred[1] > blurred[2]  # closer is cheaper
    # Distinct frames are scored once: the same values as scoring every frame.
    many = TensorDict(
        {
            "goal_pixels": goal.view(1, 1, 1, 3, 16, 16).expand(2, 40, 3, 3, 16, 16),
            ("next", "pixels"): frames.view(1, 1, 3, 3, 16, 16).expand(2, 40, 3, 3, 16, 16),
        },
        batch_size=(2, 40, 3),
    )
    cost = PixelDistanceCost(blur_sigmas=(2.0,))
    as_float = many.clone()
    as_float["next", "pixels"] = as_float["next", "pixels"].float()
    assert torch.equal(cost(many)["cost"], cost(as_float)["cost"])
    with pytest.raises(ValueError, match="blur_sigmas"):
        PixelDistanceCost(blur_sigmas=(0.0,))


def test_blurred_pixel_distance_grows_all_the_way_to_the_corner():
    """With zero padding a block in a corner lost blurred mass and looked closer."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(1,), seed=0)
    goal = env.render_state(torch.tensor([[[12, 12]]]))
    states = torch.tensor([[[k, k]] for k in range(12, -1, -1)])
    frames = env.render_state(states)
    n = states.shape[0]
    rollout = TensorDict(
        {
            ("next", "pixels"): frames.reshape(1, n, 1, 3, 16, 16),
            "goal_pixels": goal.reshape(1, 1, 1, 3, 16, 16).expand(1, n, 1, 3, 16, 16),
        },
        batch_size=(1, n, 1),
    )
    cost = PixelDistanceCost(blur_sigmas=(1.0, 2.0, 4.0)).per_step_cost(rollout).flatten()
    assert cost[0] == 0 and (cost.diff() > 0).all(), cost.tolist()


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0])
def test_blur_is_a_gaussian_with_symmetric_borders(sigma):
    """The matrix blur equals a direct sum over taps of the symmetrically padded image."""
    import numpy as np

    from dorp_rl.planners.costs.goal_image import _blur

    radius = min(15, math.ceil(3 * sigma))
    taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1) / sigma) ** 2)
    taps = (taps / taps.sum()).to(torch.float64)
    images = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)).double()
    padded = np.pad(
        images.numpy(), ((0, 0), (0, 0), (radius, radius), (radius, radius)), "symmetric"
    )
    padded = torch.from_numpy(padded)
    expected = torch.zeros_like(images)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            window = padded[..., dy : dy + 16, dx : dx + 16]
            expected += taps[dy] * taps[dx] * window
    assert torch.allclose(_blur(images, taps), expected, atol=1e-12)
    assert torch.allclose(_blur(images, taps).sum((-2, -1)), images.sum((-2, -1)))  # mass kept


def test_encoding_cache_returns_what_the_encoder_returns_across_inserts_and_resets():
    from dorp_rl.planners.costs.caches import EncodingCache

    generator = torch.Generator().manual_seed(0)
    pool = torch.randint(0, 256, (12, 3, 4, 4), dtype=torch.uint8, generator=generator)
    encoded: list[int] = []

    def encode_frames(frames):
        encoded.append(frames.shape[0])
        flat = frames.flatten(1).to(torch.int64)
        return flat[:, :2] % 7, flat[:, :6].float().reshape(-1, 2, 3) / 255

    cache = EncodingCache(size=8)
    for picks in ([0, 1, 2], [2, 3, 1, 4], [5, 6, 0], [7, 8, 9, 3], [9, 10, 11, 11]):
        frames = pool[torch.tensor(picks)]
        code, prob = cache.encode(frames, encode_frames, None)
        want_code, want_prob = encode_frames(frames)
        encoded.pop()
        assert torch.equal(code, want_code) and torch.equal(prob, want_prob)
    # [0,1,2] 3 new; [2,3,1,4] 2 new; [5,6,0] 2 new (7 held); [7,8,9,3] 3 new: full,
    # afresh; [9,10,11,11] hits 9 and encodes 10, 11 and 11 (a repeat within one call).
    assert encoded == [3, 2, 2, 3, 3]
    assert cache.count == 6
    fresh = torch.randint(0, 256, (12, 3, 4, 4), dtype=torch.uint8, generator=generator)
    code, _ = cache.encode(fresh, encode_frames, None)  # more misses than it holds
    assert torch.equal(code, encode_frames(fresh)[0]) and cache.count == 6  # not kept
