"""The fast path of planning through the true dynamics gives exactly the generic path's results.

With a :class:`~dorp_rl.envs.GroundTruthModelEnv`, planners roll candidates out on raw
states (:meth:`GroundTruthModelEnv.imagine_candidates`) and costs read lazy
:class:`~dorp_rl.envs.planning.ImaginedFrames` instead of drawn frames. The reference is
the generic TorchRL path (``env.step`` / ``step_mdp`` one step at a time, frames stacked,
the cost's ``per_step_cost``), which the planners still take for any other planning env.
Every comparison is exact (``torch.equal``), not approximate.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

import dorp_rl.envs.planning.frame_hash as frame_hash
from dorp_rl.envs import (
    GridWorldEnv,
    GroundTruthModelEnv,
    KeyWallEnv,
    ObjectRearrangementEnv,
    OracleCodeEncoder,
)
from dorp_rl.envs.planning import ImaginedFrames, distinct_rows, row_hashes
from dorp_rl.planners import (
    CategoricalCEMPlanner,
    CodeMatchCost,
    CostSequence,
    PixelDistanceCost,
    RandomShootingPlanner,
    RolloutCost,
    WeightedCostSum,
    score_rollout,
)

PIXELS = ("next", "pixels")

# Tiny tensors on a busy 2-core machine: single-threaded (conftest's fixture).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_env(kind: str, batch: int = 3, **kwargs):
    if kind == "keys":
        return KeyWallEnv(batch_size=(batch,), seed=1)
    return ObjectRearrangementEnv(num_objects=3, batch_size=(batch,), seed=1, **kwargs)


def with_codes(env, td: TensorDict) -> TensorDict:
    """Adds the oracle's codes of the goal and a per-row one-hot mask."""
    code = OracleCodeEncoder(env).encode(td["goal_pixels"])
    td["subgoal_code"] = code
    mask = torch.zeros(code.shape, dtype=torch.bool)
    mask[torch.arange(code.shape[0]), torch.arange(code.shape[0]) % code.shape[1]] = True
    td["subgoal_mask"] = mask
    return td


class StateCost(RolloutCost):
    """Reads the imagined ``("next", "state")``: the sum of its coordinates."""

    def __init__(self) -> None:
        super().__init__(step_aggregation="final")
        self.in_keys = [("next", "state")]

    def per_step_cost(self, rollout):
        return rollout["next", "state"].flatten(3).sum(-1).float()


class HalfPixelCost(PixelDistanceCost):
    """Overrides per_step_cost: the fast path must run the override on drawn frames."""

    def per_step_cost(self, rollout):
        return super().per_step_cost(rollout) / 2


def make_cost(name: str, env):
    oracle = OracleCodeEncoder(env)
    if name == "pixel":
        return PixelDistanceCost()
    if name == "blur":  # no cache between calls: each path computes its own costs
        return PixelDistanceCost(blur_sigmas=(1.0, 3.0), chunk_size=100, cache_size=0)
    if name == "code":
        return CodeMatchCost(oracle, onehots=[0], cache_size=0)
    if name == "code_mask_cached":
        return CodeMatchCost(oracle, onehots="subgoal_mask")
    if name == "state":
        return StateCost()
    if name == "override":
        return HalfPixelCost()
    return CostSequence(
        PixelDistanceCost(out_key="pixel_cost", blur_sigmas=(2.0,)),
        CodeMatchCost(oracle, onehots="subgoal_mask", out_key="code_cost"),
        WeightedCostSum({"pixel_cost": 1.0, "code_cost": 0.5}),
    )


def both_paths(planner, td, decisions):
    """Per-step costs ``[b, N, H]`` through the generic path and the fast path."""
    generic = planner.cost(planner.imagine(td, decisions).materialized())[planner.cost_key]
    rollout = planner.imagine(td, decisions)
    assert "pixels" not in rollout.td.get("next", TensorDict()).keys()  # nothing drawn up front
    fast = score_rollout(planner.cost, rollout)[planner.cost_key]
    return generic, fast


def takes_fast_path(planner, td) -> bool:
    """Whether the planning env imagines the candidates for the keys the cost reads."""
    keys = [k for k in planner.cost.in_keys if isinstance(k, tuple) and k[0] == "next"]
    actions = torch.zeros(td.shape[0], 1, planner.planning_horizon, dtype=torch.long)
    return planner.env.imagine_candidates(td, actions, keys) is not None


class SteppedModel(GroundTruthModelEnv):
    """The true dynamics without the fast path: the planners step it."""

    def imagine_candidates(self, td, actions, next_keys):
        return None


def test_imagine_gives_the_states_and_frames_of_stepping_one_step_at_a_time():
    for kind in ("rearrangement", "keys"):
        env = make_env(kind)
        model = GroundTruthModelEnv(env)
        td = env.reset()
        actions = torch.randint(
            0, env.num_actions, (3, 5, 6), generator=torch.Generator().manual_seed(0)
        )
        frames = model.imagine(td["state"].unsqueeze(1), actions)
        current = td.select("state", "pixels", "goal_pixels").unsqueeze(1).expand(3, 5).clone()
        for t in range(6):
            current["action"] = actions[..., t : t + 1]
            current = model.step(current)
            assert torch.equal(frames.states[:, :, t], current["next", "state"])
            assert torch.equal(frames.pixels()[:, :, t], current["next", "pixels"])
            current = model.step_mdp(current)
    with pytest.raises(ValueError, match="action out of range"):
        model.imagine(td["state"], torch.full((3, 2), env.num_actions))


def test_frame_parts_add_up_to_the_frame_without_overlap():
    for kind in ("rearrangement", "keys"):
        env = make_env(kind, batch=64)
        state = env.reset()["state"]
        parts = env.frame_part_table()[env.frame_parts(state)].to(torch.int64)  # [64, P, 3, 16, 16]
        assert torch.equal(parts.sum(1), env.render_state(state).to(torch.int64))
        assert int((parts.amax(2) > 0).sum(1).max()) == 1  # one part per lit pixel at most


def test_imagined_frames_distinct_is_distinct_rows_of_the_drawn_frames():
    env = make_env("rearrangement", batch=4)
    td = env.reset()
    actions = torch.randint(0, 3, (4, 40, 5), generator=torch.Generator().manual_seed(1))
    frames = GroundTruthModelEnv(env).imagine(td["state"].unsqueeze(1), actions)
    flat = frames.pixels().reshape(-1, 3, 16, 16)
    # Without extra columns.
    unique, _, inverse, keys = frames.distinct()
    expected, expected_inverse = distinct_rows(flat)
    assert unique.shape[0] < flat.shape[0]  # few actions: many repeated frames
    assert torch.equal(unique, expected) and torch.equal(inverse, expected_inverse)
    assert torch.equal(keys, row_hashes(unique))
    # With an owner column (one goal per row), as the blurred pixel cost asks.
    owner = torch.arange(4).view(4, 1, 1).expand(4, 40, 5).reshape(-1, 1)
    unique, extra, inverse, keys = frames.distinct(owner)
    rows = torch.cat([flat.reshape(flat.shape[0], -1), owner.view(torch.uint8)], -1)
    expected, expected_inverse = distinct_rows(rows)
    assert torch.equal(unique.reshape(unique.shape[0], -1), expected[:, :768])
    assert torch.equal(extra.view(torch.uint8), expected[:, 768:])
    assert torch.equal(inverse, expected_inverse)
    assert torch.equal(keys, row_hashes(expected))


def test_row_hashes_tell_apart_rows_differing_in_any_byte():
    # A weight per 8-byte word let a change in a word's top byte reach only the hash's top
    # 8 bits: one frame in 50 of the key rooms (the agent in columns 7 and 15) shared its
    # hash with another, and the planners' caches then gave it the other frame's codes.
    env = KeyWallEnv(batch_size=(1,))
    table = env.frame_part_table()  # every (cell, has-key) frame
    assert (
        torch.unique(row_hashes(table)).shape[0] == torch.unique(table.flatten(1), dim=0).shape[0]
    )
    one_byte = torch.eye(768, dtype=torch.uint8) * 255  # each byte lit alone
    assert torch.unique(row_hashes(one_byte)).shape[0] == 768
    # linear in the bytes: the hash of a sum of disjoint rows is the sum of their hashes
    a, b = one_byte[7], one_byte[15] // 2
    assert row_hashes((a + b)[None]) == row_hashes(a[None]) + row_hashes(b[None])


@pytest.mark.parametrize("name", ["code_mask_cached", "blur_cached"])
def test_cached_costs_stay_right_when_hashes_collide(monkeypatch, name):
    """Frames sharing a hash are kept out of the caches keyed by hashes: later calls,
    which read the caches, score every candidate as an uncached cost does."""
    monkeypatch.setattr(
        frame_hash, "hash_weights", lambda device, n: torch.zeros(n, dtype=torch.long)
    )
    env = make_env("rearrangement", batch=2)
    td = with_codes(env, env.reset())
    if name == "blur_cached":
        cached = PixelDistanceCost(blur_sigmas=(1.0,))
        plain = PixelDistanceCost(blur_sigmas=(1.0,), cache_size=0)
    else:
        cached = make_cost(name, env)
        plain = CodeMatchCost(OracleCodeEncoder(env), onehots="subgoal_mask", cache_size=0)
    planners = [
        RandomShootingPlanner(GroundTruthModelEnv(env), cost, planning_horizon=3, num_candidates=16)
        for cost in (cached, plain)
    ]
    for seed in range(3):  # the first call fills the cache, the next ones read it
        decisions = torch.randint(0, 12, (2, 16, 3), generator=torch.Generator().manual_seed(seed))
        fast = [score_rollout(p.cost, p.imagine(td, decisions))[p.cost_key] for p in planners]
        assert torch.equal(fast[0], fast[1])


def test_squared_distances_are_exact():
    env = make_env("rearrangement", batch=4)
    td = env.reset()
    actions = torch.randint(
        0, env.num_actions, (4, 30, 5), generator=torch.Generator().manual_seed(2)
    )
    frames = GroundTruthModelEnv(env).imagine(td["state"].unsqueeze(1), actions)
    goals = td["goal_pixels"].reshape(4, -1)
    owner = torch.arange(4).view(4, 1, 1).expand(4, 30, 5).reshape(-1)
    expected = (frames.pixels().reshape(-1, 768).long() - goals[owner].long()).square().sum(-1)
    assert torch.equal(frames.squared_distances(goals, owner), expected)


@pytest.mark.parametrize("kind", ["rearrangement", "keys"])
@pytest.mark.parametrize(
    "cost_name", ["pixel", "blur", "code", "code_mask_cached", "state", "override", "composed"]
)
def test_fast_path_costs_equal_the_generic_path(kind, cost_name):
    env = make_env(kind)
    td = with_codes(env, env.reset())
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), make_cost(cost_name, env), planning_horizon=4, num_candidates=48
    )
    assert takes_fast_path(planner, td)
    gen = torch.Generator().manual_seed(3)
    for _ in range(2):  # the second call hits CodeMatchCost's cache
        decisions = torch.randint(0, env.num_actions, (3, 48, 4), generator=gen)
        generic, fast = both_paths(planner, td, decisions)
        assert torch.equal(generic, fast)


@pytest.mark.parametrize("variant", ["rs", "cem"])
def test_planners_plan_the_same_through_both_paths(variant):
    """Whole planning calls along a short episode: same actions, plans and plan costs."""

    kwargs = dict(planning_horizon=6, num_candidates=64, seed=5, action_repeat=2)
    outputs = []
    for generic in (False, True):
        cls = RandomShootingPlanner if variant == "rs" else CategoricalCEMPlanner
        if variant == "cem":
            kwargs.update(top_k=6, optim_steps=2)
        env = make_env("rearrangement", batch=3)
        model = SteppedModel(env) if generic else GroundTruthModelEnv(env)
        planner = cls(model, make_cost("composed", env), **kwargs)
        td = with_codes(env, env.reset())
        steps = env.rollout(4, planner, auto_reset=False, tensordict=td)
        outputs.append(steps.select("action", "planner_plan", "planner_cost", "planner_length"))
    assert (outputs[0] == outputs[1]).all()


def test_fallbacks_give_the_same_costs(monkeypatch):
    # Squared distances of 2**24 and more (big white blocks): the float path decides.
    env = ObjectRearrangementEnv(
        num_objects=2,
        block_shapes=(6, 8),
        colours=torch.tensor([[255, 255, 255], [255, 255, 254]]),
        batch_size=(2,),
        seed=0,
    )
    td = env.reset(
        TensorDict(
            state=torch.tensor([[[0, 0], [0, 8]]] * 2),
            goal_state=torch.tensor([[[10, 0], [10, 8]]] * 2),
            batch_size=(2,),
        ),
        set_state=True,
    )
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=3, num_candidates=16
    )
    decisions = torch.randint(0, 8, (2, 16, 3), generator=torch.Generator().manual_seed(0))
    generic, fast = both_paths(planner, td, decisions)
    assert torch.equal(generic, fast) and float(generic.max()) ** 2 * 255**2 >= 2**24

    # Overlapping start blocks (not a valid state): frames are not sums of parts.
    env = make_env("rearrangement", batch=2)
    td = with_codes(env, env.reset())
    td["state"] = torch.tensor([[[0, 0], [0, 2], [8, 8]]] * 2)
    for name in ("pixel", "blur", "code"):
        planner = RandomShootingPlanner(
            GroundTruthModelEnv(env), make_cost(name, env), planning_horizon=3, num_candidates=16
        )
        decisions = torch.randint(0, 12, (2, 16, 3), generator=torch.Generator().manual_seed(1))
        generic, fast = both_paths(planner, td, decisions)
        assert torch.equal(generic, fast)

    # Every hash colliding: deduplication gives up on both paths alike.
    monkeypatch.setattr(
        frame_hash, "hash_weights", lambda device, n: torch.zeros(n, dtype=torch.long)
    )
    env = make_env("rearrangement", batch=2)
    td = with_codes(env, env.reset())
    frames = GroundTruthModelEnv(env).imagine(td["state"], torch.zeros(2, 3, dtype=torch.long))
    assert frames.distinct()[2] is None  # no deduplication
    for name in ("blur", "code"):
        planner = RandomShootingPlanner(
            GroundTruthModelEnv(env), make_cost(name, env), planning_horizon=3, num_candidates=16
        )
        decisions = torch.randint(0, 12, (2, 16, 3), generator=torch.Generator().manual_seed(2))
        generic, fast = both_paths(planner, td, decisions)
        assert torch.equal(generic, fast)


def test_imagined_frames_of_an_env_without_parts_draw_every_frame():
    class NoParts(ObjectRearrangementEnv):
        def frame_parts(self, state):
            return None

    env = NoParts(num_objects=2, batch_size=(2,), seed=0)
    td = env.reset()
    frames = GroundTruthModelEnv(env).imagine(td["state"], torch.zeros(2, 4, dtype=torch.long))
    assert isinstance(frames, ImaginedFrames)
    assert frames.squared_distances(td["goal_pixels"].reshape(2, -1), torch.zeros(8).long()) is None
    unique, _, inverse, _ = frames.distinct()
    assert torch.equal(unique[inverse], frames.pixels().reshape(-1, 3, 16, 16))


@pytest.mark.parametrize("shapes", [(2, 4), [(1, 1), (3, 2), (2, 5), (4, 4), (1, 7)]])
def test_rearrangement_transitions_equal_transition_step_by_step(shapes):
    """Crowded grids (many blocked moves, blocks at the borders) and mixed block shapes."""
    env = ObjectRearrangementEnv(num_objects=5, block_shapes=shapes, batch_size=(6,), seed=4)
    state = env.reset()["state"].unsqueeze(1)  # [6, 1, 5, 2]
    actions = torch.randint(0, 20, (6, 50, 30), generator=torch.Generator().manual_seed(4))
    fast = env.transitions(state, actions)
    step_by_step = GridWorldEnv.transitions(env, state, actions)  # the generic loop
    assert fast.dtype == torch.int64 and fast.shape == (6, 50, 30, 5, 2)
    assert torch.equal(fast, step_by_step)
    assert not env.invalid_states(fast).any()
    moved = (fast[:, :, 1:] != fast[:, :, :-1]).flatten(3).any(-1)
    assert 0.2 < moved.float().mean() < 0.95  # both moves and blocked moves happen


def test_cem_sampling_by_binary_search_equals_counting_cdf_entries():
    env = make_env("rearrangement")
    planner = CategoricalCEMPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(), planning_horizon=6, num_candidates=500
    )
    gen = torch.Generator().manual_seed(6)
    probs = torch.rand(3, 6, env.num_actions, generator=gen)
    probs[0] = 0.0
    probs[0, :, 4] = 1.0  # a one-hot: zero-width bins on both sides
    probs[1, :, ::2] = 0.0  # empty bins between full ones
    probs = probs / probs.sum(-1, keepdim=True)
    u = torch.rand(3, 500, 6, generator=gen)
    u[2, :10] = probs[2].cumsum(-1)[:, 3]  # uniforms exactly on a bin edge
    counted = (u.unsqueeze(-1) >= probs.cumsum(-1).unsqueeze(1)).sum(-1)
    expected = counted.clamp_max(env.num_actions - 1)
    assert torch.equal(planner._sample(probs, u), expected)
    assert bool((expected[0] == 4).all())


def test_code_match_cost_draws_only_frames_its_cache_misses():
    env = make_env("rearrangement")
    td = with_codes(env, env.reset())
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), make_cost("code_mask_cached", env), planning_horizon=4
    )
    drawn = []
    render = env.render_state

    def counting_render(state):
        drawn.append(state.reshape(-1, 3, 2).shape[0])
        return render(state)

    env.render_state = counting_render
    decisions = torch.randint(0, 12, (3, 100, 4), generator=torch.Generator().manual_seed(7))
    rollout = planner.imagine(td, decisions)
    frames = rollout.lazy_value(PIXELS)
    first = score_rollout(planner.cost, rollout)["cost"]
    drawn_first = sum(drawn)
    distinct = frames.distinct()[2].max() + 1
    # An empty cache: every distinct imagined frame once, except those equal to one of the
    # 3 start frames, which are encoded first (a blocked move keeps a start frame).
    imagined = {tuple(s) for s in frames.states.flatten(0, 2).flatten(1).tolist()}
    starts = {tuple(s) for s in td["state"].flatten(1).tolist()}
    assert len(imagined) == distinct < 3 * 100 * 4 and starts & imagined
    assert drawn_first == len(imagined - starts)
    drawn.clear()
    again = score_rollout(planner.cost, planner.imagine(td, decisions))["cost"]
    assert sum(drawn) == 0 and torch.equal(first, again)  # all in the cache: none drawn
    generic = planner.cost(planner.imagine(td, decisions).materialized())["cost"]
    assert torch.equal(first, generic)


def test_code_match_cost_refuses_out_of_range_codes_on_both_paths():
    """An encoder claiming more codes than its probabilities have: gather refuses both ways."""

    class Wide(torch.nn.Module):
        code_sizes = (100, 100, 100)

        def __init__(self, env):
            super().__init__()
            self.oracle = OracleCodeEncoder(env)

        def forward(self, pixels):
            return self.oracle(pixels)

    env = make_env("rearrangement")
    td = with_codes(env, env.reset())
    td["subgoal_code"] = torch.full((3, 3), 50)
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env),
        CodeMatchCost(Wide(env), onehots=[0]),
        planning_horizon=3,
        num_candidates=8,
    )
    decisions = torch.zeros(3, 8, 3, dtype=torch.long)
    with pytest.raises(RuntimeError, match="out of bounds"):
        planner.cost(planner.imagine(td, decisions).materialized())
    with pytest.raises(RuntimeError, match="out of bounds"):
        planner.cost(planner.imagine(td, decisions))


@pytest.mark.parametrize("distinct", [1, 3])
def test_deduplication_takes_frames_whose_byte_size_is_not_a_multiple_of_8(distinct):
    """3 x 5 x 5 frames (75 bytes): the goal index and the action read back from the
    byte rows are right, also when all steps share one frame (a lone row's slice)."""
    gen = torch.Generator().manual_seed(0)
    palette = torch.randint(0, 256, (distinct, 3, 5, 5), generator=gen, dtype=torch.uint8)
    which = torch.arange(12) % distinct
    frames = palette[which].reshape(1, 3, 4, 3, 5, 5)
    goal = torch.randint(0, 256, (1, 1, 1, 3, 5, 5), generator=gen, dtype=torch.uint8)
    rollout = TensorDict(
        {"goal_pixels": goal.expand(1, 3, 4, 3, 5, 5), ("next", "pixels"): frames},
        batch_size=(1, 3, 4),
    )
    cost = PixelDistanceCost(step_aggregation="sum")(rollout)["cost"]
    expected = (frames.float() / 255 - goal.float() / 255).flatten(-3).norm(dim=-1)
    torch.testing.assert_close(cost, expected)
    actions = torch.zeros(12, dtype=torch.int64) + 3
    out_frames, out_actions, inverse = frame_hash._distinct_pairs(palette[which], actions)
    assert out_frames.shape[0] == distinct and torch.equal(out_actions[inverse], actions)
    assert torch.equal(out_frames[inverse], palette[which])
