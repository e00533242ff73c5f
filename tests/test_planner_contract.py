"""The planners' public fast-path contract: what a planning env and a cost declare.

A planning env may declare ``imagine_candidates(td, actions, next_keys)`` (candidates
rolled out without stepping, some values left lazy); every cost reads the one
:class:`~dorp_rl.planners.CandidateRollout` the planner makes, and may read a lazy value
for less (``rollout.lazy_value``, ``rollout.frames``). So every combination plans exactly
as stepping the env one step at a time and calling the cost on computed values does.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import Transform

from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.envs.planning import ImaginedFrames, LazyValue
from dorp_rl.planners import (
    CandidateRollout,
    CategoricalCEMPlanner,
    CodeMatchCost,
    CostSequence,
    PixelDistanceCost,
    RandomShootingPlanner,
    RolloutCost,
    WeightedCostSum,
    score_rollout,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

POSITION = ("next", "position")
PIXELS = ("next", "pixels")
PLAN_KEYS = ("action", "planner_plan", "planner_cost", "planner_length")


# --------------------------------------------------------------------------- #
# A planning env of the test's own: a point on a line
# --------------------------------------------------------------------------- #
class LineEnv(EnvBase):
    """A point on ``[0, 20]``: action 0 moves it left, 1 keeps it, 2 moves it right.

    Stateless with any leading shape; it declares no ``imagine_candidates``, so the
    planners step it.
    """

    def __init__(self) -> None:
        super().__init__(batch_size=())
        self.__dict__["_batch_locked"] = False
        self.steps = 0
        self.observation_spec = Composite(
            position=Bounded(low=0, high=20, shape=(1,), dtype=torch.int64)
        )
        self.action_spec = Categorical(3, shape=(1,), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)

    def _reset(self, td=None, **kwargs):
        shape = td.batch_size if td is not None else torch.Size([])
        zeros = torch.zeros(*shape, 1, dtype=torch.int64)
        return TensorDict(position=zeros + 10, done=zeros.bool(), batch_size=shape)

    def _step(self, td):
        self.steps += 1
        position = (td["position"] + td["action"] - 1).clamp(0, 20)
        false = torch.zeros_like(position, dtype=torch.bool)
        return TensorDict(
            position=position,
            reward=torch.zeros(position.shape, dtype=torch.float32),
            done=false,
            terminated=false.clone(),
            batch_size=td.batch_size,
        )

    def _set_seed(self, seed):
        pass


class Positions:
    """A lazy ``("next", "position")``: counts how often it is materialised."""

    def __init__(self, values: torch.Tensor) -> None:
        self.values = values
        self.materialized = 0

    def materialize(self) -> torch.Tensor:
        self.materialized += 1
        return self.values


class ImaginingLineEnv(LineEnv):
    """The same dynamics, and candidates imagined without stepping (positions lazy)."""

    def __init__(self) -> None:
        super().__init__()
        self.imagined: list[Positions] = []

    def imagine_candidates(self, td, actions, next_keys):
        if next_keys is None or any(key != POSITION for key in next_keys):
            return None
        position = td["position"].unsqueeze(1).expand(*actions.shape[:2], 1)
        positions = []
        for t in range(actions.shape[-1]):
            position = (position + actions[..., t : t + 1] - 1).clamp(0, 20)
            positions.append(position)
        rollout = TensorDict(action=actions.unsqueeze(-1), batch_size=actions.shape)
        lazy = Positions(torch.stack(positions, dim=2))  # [b, N, H, 1]
        self.imagined.append(lazy)
        return rollout, {POSITION: lazy} if POSITION in next_keys else {}


class DecliningLineEnv(LineEnv):
    """Declares ``imagine_candidates`` but declines every request: the planner steps it."""

    def imagine_candidates(self, td, actions, next_keys):
        return None


class DistanceToTarget(RolloutCost):
    """``|position - target|`` per step; knows nothing of lazy values."""

    def __init__(self, **kwargs) -> None:
        super().__init__(step_aggregation="min", **kwargs)
        self.in_keys = [POSITION, "target"]

    def per_step_cost(self, rollout):
        return (rollout[POSITION] - rollout["target"]).abs().squeeze(-1).to(torch.float32)


class LazyDistanceToTarget(DistanceToTarget):
    """The same cost, reading a lazy position without materialising it."""

    def per_step_cost(self, rollout):
        positions = rollout.lazy_value(POSITION)
        if not isinstance(positions, Positions):
            return super().per_step_cost(rollout)
        return (positions.values - rollout["target"]).abs().squeeze(-1).to(torch.float32)


def line_rows(rows: int = 3) -> TensorDict:
    return TensorDict(
        position=torch.tensor([[2], [10], [19]])[:rows],
        target=torch.tensor([[7], [3], [15]])[:rows],
        batch_size=(rows,),
    )


def plan(planner_cls, env, cost, td, **kwargs) -> TensorDict:
    if planner_cls is CategoricalCEMPlanner:
        kwargs = {"optim_steps": 2, "top_k": 5, **kwargs}
    planner = planner_cls(env, cost, planning_horizon=6, num_candidates=40, seed=3, **kwargs)
    return planner(td.clone()).select(*PLAN_KEYS)


@pytest.mark.parametrize("planner_cls", [RandomShootingPlanner, CategoricalCEMPlanner])
def test_an_env_imagining_candidates_plans_as_stepping_it(planner_cls):
    td = line_rows()
    stepped_env = LineEnv()
    stepped = plan(planner_cls, stepped_env, DistanceToTarget(), td)
    assert stepped_env.steps > 0
    imagining = ImaginingLineEnv()
    for cost in (DistanceToTarget(), LazyDistanceToTarget()):
        out = plan(planner_cls, imagining, cost, td)
        assert (out == stepped).all()
    assert imagining.steps == 0  # never stepped
    lazy = imagining.imagined
    calls = 1 if planner_cls is RandomShootingPlanner else 2
    assert len(lazy) == 2 * calls
    # The plain cost got its lazy positions materialised, the lazy one read them as such.
    assert [v.materialized for v in lazy] == [1] * calls + [0] * calls
    # Declining (or declaring nothing) means stepping, with the same plans.
    declining = DecliningLineEnv()
    assert (plan(planner_cls, declining, DistanceToTarget(), td) == stepped).all()
    assert declining.steps > 0


def test_an_env_imagining_candidates_is_stepped_for_keys_it_cannot_imagine():
    class ReadsReward(DistanceToTarget):
        def __init__(self):
            super().__init__()
            self.in_keys = [POSITION, "target", ("next", "reward")]

    env = ImaginingLineEnv()
    out = plan(RandomShootingPlanner, env, ReadsReward(), line_rows())
    assert env.steps == 6 and not env.imagined
    assert (out == plan(RandomShootingPlanner, LineEnv(), ReadsReward(), line_rows())).all()


def test_a_composed_cost_of_a_line_env_plans_alike_in_every_composition():
    td = line_rows()
    reference = plan(
        RandomShootingPlanner,
        LineEnv(),
        TensorDictSequential(
            DistanceToTarget(out_key="d"), WeightedCostSum({"d": 2.0}, step_aggregation="min")
        ),
        td,
    )
    for sequence in (CostSequence, TensorDictSequential):
        for member in (DistanceToTarget, LazyDistanceToTarget):
            env = ImaginingLineEnv()
            cost = sequence(
                member(out_key="d"), WeightedCostSum({"d": 2.0}, step_aggregation="min")
            )
            assert (plan(RandomShootingPlanner, env, cost, td) == reference).all()
            lazy_read = sequence is CostSequence and member is LazyDistanceToTarget
            assert env.imagined[0].materialized == (0 if lazy_read else 1)


def test_a_bad_imagine_candidates_result_is_refused():
    class WrongShape(LineEnv):
        def imagine_candidates(self, td, actions, next_keys):
            return TensorDict(
                action=actions[:, :1].unsqueeze(-1), batch_size=actions[:, :1].shape
            ), {}

    class Missing(LineEnv):
        def imagine_candidates(self, td, actions, next_keys):
            return TensorDict(action=actions.unsqueeze(-1), batch_size=actions.shape), {}

    with pytest.raises(ValueError, match=r"batch shape \[3, 40, 6\]"):
        plan(RandomShootingPlanner, WrongShape(), DistanceToTarget(), line_rows())
    with pytest.raises(ValueError, match="returned no \\('next', 'position'\\)"):
        plan(RandomShootingPlanner, Missing(), DistanceToTarget(), line_rows())


# --------------------------------------------------------------------------- #
# The true dynamics: lazy frames
# --------------------------------------------------------------------------- #
class SteppedModel(GroundTruthModelEnv):
    """The true dynamics, declining the fast path: the planners step it."""

    def imagine_candidates(self, td, actions, next_keys):
        return None


class HalfPixelCost(PixelDistanceCost):
    """A user's cost: overrides ``per_step_cost`` (the one method a cost has)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.saw_pixels: list[bool] = []

    def per_step_cost(self, rollout):
        self.saw_pixels.append(PIXELS in rollout)
        return super().per_step_cost(rollout) / 2


class DoubledForward(PixelDistanceCost):
    """A user's cost: overrides ``forward`` (after the base class's)."""

    def forward(self, rollout):
        rollout = super().forward(rollout)
        rollout.set(self.out_key, rollout.get(self.out_key) * 2)
        return rollout


def rearrangement(batch: int = 2):
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(batch,), seed=0)
    td = env.reset()
    td["subgoal_code"] = OracleCodeEncoder(env).encode(td["goal_pixels"])
    return env, td


def plan_gt(model, cost, td, **kwargs) -> TensorDict:
    planner = RandomShootingPlanner(
        model, cost, planning_horizon=4, num_candidates=48, seed=1, **kwargs
    )
    return planner(td.clone()).select(*PLAN_KEYS)


def test_a_cost_overriding_per_step_cost_in_a_cost_sequence_gets_its_override():
    env, td = rearrangement()
    plain = plan_gt(GroundTruthModelEnv(env), PixelDistanceCost(), td)
    half = HalfPixelCost(out_key="half")
    cost = CostSequence(
        PixelDistanceCost(out_key="pixel"),  # reads the lazy frames
        half,  # its override runs, on the same rollout
        WeightedCostSum({"half": 1.0, "pixel": 0.0}, step_aggregation="min"),
    )
    out = plan_gt(GroundTruthModelEnv(env), cost, td)
    assert half.saw_pixels == [True]
    assert torch.equal(out["planner_cost"], plain["planner_cost"] / 2)
    assert torch.equal(out["planner_plan"], plain["planner_plan"])
    assert (out == plan_gt(SteppedModel(env), cost, td)).all()
    # Alone, the same.
    alone = plan_gt(GroundTruthModelEnv(env), HalfPixelCost(), td)
    assert torch.equal(alone["planner_cost"], plain["planner_cost"] / 2)


class CountingPixelCost(PixelDistanceCost):
    """A pixel distance that counts the rollouts it scored."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.calls = 0

    def per_step_cost(self, rollout):
        self.calls += 1
        return super().per_step_cost(rollout)


@pytest.mark.parametrize("sequence", ["plain", "lazy"])
def test_a_term_weighted_zero_in_every_row_is_not_computed(sequence):
    env, td = rearrangement()
    td["term_weight"] = torch.zeros(2, 1)
    counted = CountingPixelCost(out_key="counted", blur_sigmas=(2.0,))
    cost = CostSequence(
        PixelDistanceCost(out_key="pixel"),
        counted,
        WeightedCostSum({"pixel": 1.0, "counted": "term_weight"}, step_aggregation="min"),
    )
    model = SteppedModel(env) if sequence == "plain" else GroundTruthModelEnv(env)
    plain = plan_gt(model, PixelDistanceCost(), td)
    out = plan_gt(model, cost, td)
    assert counted.calls == 0
    assert torch.equal(out["planner_cost"], plain["planner_cost"])
    assert torch.equal(out["planner_plan"], plain["planner_plan"])
    # One row weighing the term: it is computed for the call, and counts in that row.
    td["term_weight"] = torch.tensor([[0.0], [5.0]])
    out = plan_gt(model, cost, td)
    assert counted.calls == 1
    assert torch.equal(out["planner_cost"][0], plain["planner_cost"][0])
    assert float(out["planner_cost"][1]) > float(plain["planner_cost"][1])


def test_a_zero_weighted_term_another_cost_reads_is_still_computed():
    env, td = rearrangement()
    td["term_weight"] = torch.zeros(2, 1)
    counted = CountingPixelCost(out_key="counted")
    cost = CostSequence(
        counted,
        WeightedCostSum({"counted": 2.0}, out_key="doubled"),
        WeightedCostSum({"counted": "term_weight", "doubled": 1.0}, step_aggregation="min"),
    )
    out = plan_gt(GroundTruthModelEnv(env), cost, td)
    plain = plan_gt(GroundTruthModelEnv(env), PixelDistanceCost(), td)
    assert counted.calls == 1
    assert torch.equal(out["planner_cost"], 2 * plain["planner_cost"])


def test_a_cost_overriding_forward_gets_its_override_on_drawn_frames():
    env, td = rearrangement()
    plain = plan_gt(GroundTruthModelEnv(env), PixelDistanceCost(), td)
    for cost in (DoubledForward(), CostSequence(DoubledForward())):
        out = plan_gt(GroundTruthModelEnv(env), cost, td, step_aggregation="min")
        assert torch.equal(out["planner_cost"], plain["planner_cost"] * 2)
        assert (out == plan_gt(SteppedModel(env), cost, td, step_aggregation="min")).all()


def test_a_cost_reads_imagined_frames_as_it_reads_drawn_ones():
    env, td = rearrangement()
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), PixelDistanceCost(blur_sigmas=(2.0,)), planning_horizon=3
    )
    decisions = torch.randint(0, 8, (2, 16, 3), generator=torch.Generator().manual_seed(0))
    rollout = planner.imagine(td, decisions)
    imagined = rollout.lazy_value(PIXELS)
    assert isinstance(imagined, ImaginedFrames) and isinstance(imagined, LazyValue)
    assert PIXELS not in rollout.td.keys(True, True) and PIXELS in rollout
    assert rollout.frames(PIXELS) is imagined  # frames stay undrawn for the cost
    fast = planner.cost(rollout)["cost"]
    assert PIXELS not in rollout.td.keys(True, True)  # the cost drew only distinct frames
    drawn = planner.imagine(td, decisions).materialized()
    assert torch.equal(drawn[PIXELS], imagined.pixels())
    assert torch.equal(fast, planner.cost(drawn)["cost"])
    # get() computes a lazy value once and keeps it
    again = planner.imagine(td, decisions)
    assert again.get(PIXELS) is again.get(PIXELS) and again.lazy_value(PIXELS) is None


def test_a_plain_tensordict_sequential_cost_works_with_the_true_dynamics():
    env, td = rearrangement()
    oracle = OracleCodeEncoder(env)

    def members():
        return (
            PixelDistanceCost(out_key="pixel", blur_sigmas=(1.0,)),
            CodeMatchCost(oracle, onehots=[0], out_key="code", cache_size=0),
            WeightedCostSum({"pixel": 0.01, "code": 1.0}, step_aggregation="min"),
        )

    plain = plan_gt(GroundTruthModelEnv(env), TensorDictSequential(*members()), td)
    assert (plain == plan_gt(GroundTruthModelEnv(env), CostSequence(*members()), td)).all()
    assert (plain == plan_gt(SteppedModel(env), TensorDictSequential(*members()), td)).all()
    # Through score_rollout a plain sequence gets the frames drawn into the rollout.
    planner = RandomShootingPlanner(
        GroundTruthModelEnv(env), TensorDictSequential(*members()), planning_horizon=3
    )
    decisions = torch.zeros(2, 4, 3, dtype=torch.long)
    rollout = planner.imagine(td, decisions)
    assert isinstance(rollout, CandidateRollout) and rollout.lazy_value(PIXELS) is not None
    assert PIXELS in score_rollout(planner.cost, rollout).keys(True, True)


def test_an_env_subclass_overriding_step_is_stepped_through_its_step():
    class Frozen(GroundTruthModelEnv):
        """Nothing ever moves: every candidate's frames are the start frame."""

        def _step(self, td):
            self.__dict__["steps"] = self.__dict__.get("steps", 0) + 1
            return self._outputs(
                td.batch_size, td["pixels"], td.get("goal_pixels"), reward=True, state=td["state"]
            )

    class FrozenImagining(Frozen):
        """Declares an imagine_candidates of its own, for its own dynamics: it is used."""

        def imagine_candidates(self, td, actions, next_keys):
            assert super().imagine_candidates(td, actions, next_keys) is None
            self.__dict__["imagined"] = True
            rollout = TensorDict(action=actions.unsqueeze(-1), batch_size=actions.shape)
            shape = (*actions.shape, *td["pixels"].shape[1:])
            rollout.set(PIXELS, td["pixels"][:, None, None].expand(shape))
            return rollout, {}

    env, td = rearrangement()
    model = Frozen(env)
    assert model.imagine_candidates(td, torch.zeros(2, 1, 4, dtype=torch.long), [PIXELS]) is None
    out = plan_gt(model, PixelDistanceCost(), td)
    assert model.__dict__["steps"] == 4  # one call of the horizon's 4 steps
    start = PixelDistanceCost()(
        TensorDict(
            {PIXELS: td["pixels"].unsqueeze(1), "goal_pixels": td["goal_pixels"].unsqueeze(1)},
            batch_size=(2, 1),
        )
    )["cost"]
    assert torch.equal(out["planner_cost"], start)  # planned with the frozen dynamics
    assert not torch.equal(
        out["planner_cost"],
        plan_gt(GroundTruthModelEnv(env), PixelDistanceCost(), td)["planner_cost"],
    )
    both = FrozenImagining(env)
    assert (plan_gt(both, PixelDistanceCost(), td) == out).all()
    assert both.__dict__.get("imagined") and "steps" not in both.__dict__


def test_a_transformed_true_dynamics_env_is_stepped_through_its_transforms():
    class CountSteps(Transform):
        def __init__(self):
            super().__init__()
            self.count = 0

        def _step(self, tensordict, next_tensordict):
            self.count += 1
            return next_tensordict

    env, td = rearrangement()
    counter = CountSteps()
    wrapped = TransformedEnv(GroundTruthModelEnv(env), counter)
    out = plan_gt(wrapped, PixelDistanceCost(), td)
    assert counter.count == 4
    assert (out == plan_gt(GroundTruthModelEnv(env), PixelDistanceCost(), td)).all()


def test_cost_sequence_is_a_tensordict_sequential_of_costs_in_order():
    a, b = PixelDistanceCost(out_key="a"), WeightedCostSum({"a": 3.0})
    sequence = CostSequence(a, b)
    assert isinstance(sequence, TensorDictSequential) and len(sequence) == 2
    assert sequence[0] is a and sequence.out_keys == ["a", "cost"]
    assert CostSequence([a, b]).in_keys == sequence.in_keys == [PIXELS, "goal_pixels"]
    with pytest.raises(ValueError, match="in order"):
        CostSequence({"a": a, "b": b})


def test_a_rearrangement_subclass_changing_transition_is_imagined_with_its_transition():
    class NoMoves(ObjectRearrangementEnv):
        def transition(self, state, action):
            return state.clone()

    class NoMovesEither(NoMoves):
        def transitions(self, state, actions):  # a wrapper: still NoMoves' moves
            return super().transitions(state, actions)

    for cls in (NoMoves, NoMovesEither):
        env = cls(num_objects=2, batch_size=(2,), seed=0)
        state = env.reset()["state"].unsqueeze(1)
        actions = torch.randint(0, 8, (2, 5, 3), generator=torch.Generator().manual_seed(0))
        expected = state.unsqueeze(2).expand(2, 5, 3, 2, 2)
        assert torch.equal(env.transitions(state, actions), expected)
        frames = GroundTruthModelEnv(env).imagine(state, actions)
        assert torch.equal(frames.states, expected)
