"""The planning envs honour torchrl's contract for stateless envs and goals given as images.

- :class:`~dorp_rl.envs.planning.StatelessEnvModel` hands a user's env every entry its
  observation spec declares (``step_count`` here), through a whole DORP plan, and names
  an entry its ``_step`` looks up and does not find;
- with a fixed batch it steps the whole flat batch at once when a probe finds that exact;
- every planning env takes a goal given as an image only (``goal_pixels``, no
  ``goal_state``), :class:`~dorp_rl.envs.GymGoalEnv` over MiniGrid included;
- the hashes that deduplicate imagined frames are the weighted byte sums they were.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from push_blocks import PushBlocksEnv
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, VideoModelEnv
from dorp_rl.envs.planning import StatelessEnvModel, distinct_rows, frame_hash, row_hashes
from dorp_rl.planners import CodeGraph, PixelDistanceCost, RandomShootingPlanner

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class CountingBlocksEnv(PushBlocksEnv):
    """PushBlocksEnv that declares ``step_count`` int64 ``[*B, 1]`` and reads it in
    ``_step`` (as torchrl's stateless envs read their observation entries); records the
    counts and batch shapes its ``_step`` is handed."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.observation_spec["step_count"] = Unbounded((*self.batch_size, 1), dtype=torch.int64)
        self.seen: list[torch.Tensor] = []
        self.step_shapes: list[tuple[int, ...]] = []

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        out = super()._reset(tensordict, **kwargs)
        given = tensordict.get("step_count", None) if kwargs.get("set_state") else None
        zero = torch.zeros(*out.batch_size, 1, dtype=torch.int64)
        out.set("step_count", zero if given is None else given.clone())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        count = tensordict["step_count"]
        self.seen.append(count.reshape(-1).clone())
        self.step_shapes.append(tuple(tensordict.batch_size))
        out = super()._step(tensordict)
        out.set("step_count", count + 1)
        return out


def candidates(model, rows: int = 3, n: int = 5, seed: int = 0) -> TensorDict:
    """``[rows, n]`` copies of the first reset rows with random actions."""
    td = model.true_env.reset()[:rows].unsqueeze(1).expand(rows, n).clone()
    gen = torch.Generator().manual_seed(seed)
    td["action"] = torch.randint(0, 8, (rows, n, 1), generator=gen)
    return td


def test_the_model_hands_the_env_every_declared_entry():
    env = CountingBlocksEnv((1, 8, 8), batch_size=(4,), seed=0)
    model = StatelessEnvModel(env)
    assert "step_count" in model.observation_spec.keys()
    td = candidates(model)
    td["step_count"] = torch.arange(15).reshape(3, 5, 1)
    out = model.step(td)["next"]
    assert torch.equal(out["step_count"], td["step_count"] + 1)
    # Row by row the env itself gives the same next state and count.
    free = CountingBlocksEnv((1, 8, 8), batch_size=(), batch_locked=False)
    for i, j in ((0, 0), (2, 4)):
        one = free._step(td[i, j].clone())
        assert torch.equal(one["state"], out["state"][i, j])
        assert torch.equal(one["step_count"], out["step_count"][i, j])
    # A goal is not needed to imagine a step; filled-in goals are not written back.
    bare = td.select("state", "step_count", "action")
    out = model.step(bare)["next"]
    assert "goal_state" not in out.keys() and "goal_pixels" not in out.keys()
    assert torch.equal(out["step_count"], td["step_count"] + 1)


def test_a_missing_entry_is_a_value_error_naming_it_the_env_and_the_model():
    model = StatelessEnvModel(CountingBlocksEnv((1, 8, 8), batch_size=(4,)))
    td = candidates(model).exclude("step_count")
    with pytest.raises(ValueError, match="CountingBlocksEnv._step looked up 'step_count'") as err:
        model.step(td)
    text = str(err.value)
    assert "StatelessEnvModel" in text and "dorp_rl.envs.planning" in text
    assert "is in CountingBlocksEnv's observation spec" in text and "reset writes it" in text
    assert isinstance(err.value, KeyError)  # callers catching a KeyError still do

    class Undeclared(PushBlocksEnv):
        def _step(self, tensordict):
            tensordict["step_count"]
            return super()._step(tensordict)

    model = StatelessEnvModel(Undeclared((1, 8, 8), batch_size=(4,)))
    with pytest.raises(ValueError, match="'step_count' is not in Undeclared's observation spec"):
        model.step(candidates(model))


class WithParams(PushBlocksEnv):
    """Reads ``("params", "speed")`` of its state spec (torchrl's stateless ``params``)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        b = self.batch_size
        speed = Unbounded((*b, 1), dtype=torch.int64)
        self.state_spec = Composite(params=Composite(speed=speed, shape=b), shape=b)
        self.speeds: list[torch.Tensor] = []

    def _reset(self, tensordict=None, **kwargs):
        out = super()._reset(tensordict, **kwargs)
        given = tensordict.get("params", None) if kwargs.get("set_state") else None
        speed = torch.full((*out.batch_size, 1), 3, dtype=torch.int64)
        params = TensorDict(speed=speed, batch_size=out.batch_size)
        out.set("params", params if given is None else given.clone())
        return out

    def _step(self, tensordict):
        self.speeds.append(tensordict["params", "speed"].reshape(-1).clone())
        return super()._step(tensordict)


def test_state_spec_entries_ride_through_a_plan():
    env = WithParams((1, 8, 8), batch_size=(2,))
    model = StatelessEnvModel(env)
    assert ("params", "speed") in model.full_state_spec.keys(True, True)
    planner = RandomShootingPlanner(
        model, PixelDistanceCost(), planning_horizon=3, num_candidates=4, seed=0
    )
    td = env.reset()
    td["params", "speed"] = torch.tensor([[5], [7]])
    env.speeds.clear()
    planner(td)
    # Every imagined step read its acting row's speed (3 steps of 2 x 4 candidates; the
    # probe on the first step reads them once more), never the reset's 3.
    seen = torch.cat(env.speeds)
    assert int((seen == 5).sum()) == int((seen == 7).sum()) == 4 * 4
    assert seen.numel() == 2 * 4 * 4


class BlockCells(torch.nn.Module):
    """Codes of PushBlocksEnv frames: per block, the 4 x 4 quadrant of its top-left cell."""

    code_sizes = (4, 4)

    def __init__(self, env: PushBlocksEnv) -> None:
        super().__init__()
        self.register_buffer("shades", env.shades.clone())

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codes = []
        for shade in self.shades:
            mask = (pixels == shade.view(-1, 1, 1)).all(-3)
            row = mask.any(-1).to(torch.int64).argmax(-1)
            col = mask.any(-2).to(torch.int64).argmax(-1)
            codes.append((row // 4) * 2 + col // 4)
        code = torch.stack(codes, -1)
        return code, torch.nn.functional.one_hot(code, 4).float()

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor) -> torch.Tensor:
        return self(torch.as_tensor(pixels))[0]


def test_step_count_reaches_the_model_through_a_dorp_plan():
    """DORP with the true dynamics of an env fixed at batch (2,): the planning model is
    StatelessEnvModel over the acting env, and imagined steps count on from the acting
    env's step_count (up to the acting count + horizon)."""
    from dorp_rl.policies import make_dorp_policy

    env = CountingBlocksEnv((3, 8, 8), batch_size=(2,), seed=1)
    encoder = BlockCells(env)
    # Every move from 64 random states: a graph of all the quadrant hops.
    free = PushBlocksEnv((3, 8, 8), batch_size=(), batch_locked=False)
    starts = free.reset(TensorDict(batch_size=[64]))
    step = starts.unsqueeze(1).expand(64, 8).clone()
    step["action"] = torch.arange(8).expand(64, 8).unsqueeze(-1).clone()
    after = free._step(step)
    codes = encoder.encode(step["pixels"]).reshape(-1, 2)
    graph = CodeGraph.from_transitions(
        codes,
        encoder.encode(after["pixels"]).reshape(-1, 2),
        encoder.code_sizes,
        actions=step["action"].reshape(-1),
        num_actions=8,
    )
    horizon = 4
    policy = make_dorp_policy(
        env, encoder, graph, seed=0, num_candidates=16, planning_horizon=horizon
    )
    assert isinstance(policy.waypoint_planner.env, StatelessEnvModel)
    start = torch.tensor([[[0, 0], [5, 6]], [[6, 0], [0, 7]]])
    goal = torch.tensor([[[6, 5], [0, 0]], [[0, 5], [5, 0]]])
    td = env.reset(TensorDict(state=start, goal_state=goal, batch_size=[2]), set_state=True)
    env.seen.clear()
    rollout = env.rollout(3, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    assert torch.equal(rollout["next", "step_count"][:, -1], torch.full((2, 1), 3))
    seen = torch.cat(env.seen)
    # Acting steps count 0..2; imagined ones start there and run on for the horizon.
    assert int(seen.max()) >= horizon > 2 and int(seen.min()) == 0


class ReshapesToItsBatch(PushBlocksEnv):
    """A stateless env whose ``_step`` only takes its own batch (reshapes to it)."""

    def _step(self, tensordict):
        out = super()._step(tensordict.reshape(self.batch_size))
        return out.reshape(tensordict.batch_size)


class MovesOnlyInFours(PushBlocksEnv):
    """A stateless env whose steps differ when handed a batch of another size."""

    def _step(self, tensordict):
        out = super()._step(tensordict)
        if tensordict.batch_size[0] != 4:
            out.set("state", tensordict["state"].clone())
        return out


def outputs(td: TensorDictBase) -> dict:
    return {k: v for k, v in td["next"].items(True, True)}


@pytest.mark.parametrize(
    "env_class, whole",
    [(CountingBlocksEnv, True), (ReshapesToItsBatch, False), (MovesOnlyInFours, False)],
)
def test_a_fixed_batch_steps_at_once_only_where_that_is_exact(env_class, whole):
    """A probe on the first step decides; the outputs are the chunks' either way."""
    env = env_class((1, 8, 8), batch_size=(4,), seed=2)
    model = StatelessEnvModel(env)
    chunked = StatelessEnvModel(env_class((1, 8, 8), batch_size=(4,), seed=2))
    chunked.whole_batch = False  # the reference: chunks of 4, the last one padded
    for seed in range(3):
        td = candidates(model, seed=seed)
        if env_class is CountingBlocksEnv:
            td["step_count"] = torch.arange(15).reshape(3, 5, 1)
        got, expected = outputs(model.step(td.clone())), outputs(chunked.step(td.clone()))
        assert got.keys() == expected.keys()
        assert all(torch.equal(got[k], expected[k]) for k in expected)
    assert model.whole_batch is whole
    if whole:  # after the probe: one call of all 15 rows per step
        env.step_shapes.clear()
        model.step(candidates(model))
        assert env.step_shapes == [(15,)]


def door_key(monkeypatch):
    pytest.importorskip("minigrid")
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples"))
    import gymnasium_env

    return gymnasium_env


def test_gym_goal_env_takes_a_goal_given_as_an_image_only(monkeypatch):
    """GymGoalEnv over MiniGrid DoorKey: a step, a reset and a planner's step on a
    tensordict holding goal_pixels without goal_state; solved when the frame equals it."""
    dk = door_key(monkeypatch)
    env = dk.make_env(batch_size=(2,), seed=0)
    model = dk.make_env(batch_size=(), seed=0)
    td = env.reset()
    moved = env.step(td.clone().set("action", torch.tensor([[2], [0]])))["next"]
    goal_only = td.exclude("goal_state").set("goal_pixels", moved["pixels"].clone())
    # Step: the goal image of the next frame is reached, another is not.
    for action, solved in ((torch.tensor([[2], [0]]), True), (torch.tensor([[1], [1]]), False)):
        out = env.step(goal_only.clone().set("action", action))["next"]
        assert "goal_state" not in out.keys()
        assert torch.equal(out["goal_pixels"], moved["pixels"])
        assert bool(out["done"].all()) is solved
    # Reset keeps a goal image given without a goal state.
    again = env.reset(goal_only.select("state", "goal_pixels"), set_state=True)
    assert torch.equal(again["goal_pixels"], moved["pixels"]) and "goal_state" not in again.keys()
    # A planner over the env itself (batch ()) and over its fixed batch plans toward it.
    for planning_env in (model, StatelessEnvModel(env)):
        planner = RandomShootingPlanner(
            planning_env, PixelDistanceCost(), planning_horizon=2, num_candidates=8, seed=0
        )
        rollout = env.rollout(
            2, planner, tensordict=again, auto_reset=False, break_when_any_done=False
        )
        assert rollout["next", "done"][:, 0].all()  # one step from the goal image: taken
    # A frame that cannot be the goal's: never solved.
    with_other_goal = goal_only.set("goal_pixels", torch.zeros_like(moved["pixels"]))
    assert not env.step(with_other_goal.set("action", torch.tensor([[2], [0]])))[
        "next", "done"
    ].any()


class ShiftModel:
    """Adds ``10 * action`` to every byte of the frame (mod 256)."""

    def predict(self, pixels, action, deterministic=True):
        return ((pixels.to(torch.int64) + 10 * action.view(-1, 1, 1, 1)) % 256).to(torch.uint8)


@pytest.mark.parametrize("name", ["ground-truth", "world-model", "stateless", "stateless-counting"])
def test_every_planning_env_plans_toward_a_goal_given_as_an_image_only(name):
    if name in ("ground-truth", "world-model"):
        env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        model = (
            GroundTruthModelEnv(env) if name == "ground-truth" else VideoModelEnv(ShiftModel(), 8)
        )
    else:
        env_class = CountingBlocksEnv if name == "stateless-counting" else PushBlocksEnv
        env = env_class((3, 8, 8), batch_size=(2,), seed=0)
        model = StatelessEnvModel(env)
    td = env.reset()
    goal = td["goal_pixels"].clone()
    td = td.exclude("goal_state")
    planner = RandomShootingPlanner(
        model, PixelDistanceCost(), planning_horizon=3, num_candidates=16, seed=0
    )
    out = planner(td.clone())
    assert out["action"].shape == (2, 1) and torch.equal(out["goal_pixels"], goal)
    assert int(out["planner_length"].min()) >= 1


def reference_hashes(rows: torch.Tensor) -> torch.Tensor:
    """The weighted byte sums modulo 2**64 that row_hashes is defined as."""
    flat = rows.reshape(rows.shape[0], -1)
    weights = frame_hash.hash_weights(rows.device, flat.shape[1])
    return (flat.to(torch.int64) * weights).sum(-1)


@pytest.mark.parametrize("width", [1, 7, 40, 768, 3 * 76 * 76, 131_064 + 13])
def test_row_hashes_are_the_weighted_byte_sums_at_any_width(width):
    gen = torch.Generator().manual_seed(width)
    rows = torch.randint(0, 256, (6, width), dtype=torch.uint8, generator=gen)
    rows[0] = 255  # the largest terms
    rows[1] = 0
    assert torch.equal(row_hashes(rows), reference_hashes(rows))
    assert torch.equal(row_hashes(rows[1:]), reference_hashes(rows[1:]))  # an unaligned view
    assert row_hashes(rows[:0]).shape == (0,)


def test_distinct_rows_are_exact_on_large_frames_and_give_up_on_collisions(monkeypatch):
    gen = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 256, (5, 3 * 76 * 76), dtype=torch.uint8, generator=gen)
    pick = torch.randint(0, 5, (300,), generator=gen)
    for rows in (frames[pick], frames[pick][1:], frames[pick][:, 3:]):
        unique, inverse = distinct_rows(rows)
        assert unique.shape[0] == 5 and torch.equal(unique[inverse], rows)
    # Every hash equal: the rows are compared, so different rows are never merged.
    monkeypatch.setattr(
        frame_hash, "hash_weights", lambda device, n: torch.zeros(n, dtype=torch.long)
    )
    rows = frames[pick]
    unique, inverse = distinct_rows(rows)
    assert inverse is None and unique is rows
    unique, inverse = distinct_rows(frames[[2, 2, 2]])
    assert unique.shape[0] == 1 and inverse.tolist() == [0, 0, 0]
