"""Costs of imagined rollouts: TensorDict modules that the discrete MPC planners minimise.

A planner rolls ``N`` candidate action sequences of ``H`` steps out for each of ``B``
acting envs and hands the cost one tensordict of batch shape ``[B, N, H]``:

- ``action``: int64 ``[B, N, H, 1]``, the action taken at each step;
- ``("next", key)``: what the planning env produced after each step, e.g.
  ``("next", "pixels")`` uint8 ``[B, N, H, C, H', W']``, the predicted frames;
- any other root key: the acting env's tensordict at planning time (the start of the
  rollout), broadcast without copies over candidates and steps. So root ``pixels`` is
  the *start* frame at every step, and ``goal_pixels`` / ``subgoal_code`` are the goal
  of each row.

Each cost is a :class:`~tensordict.nn.TensorDictModuleBase`: it reads its ``in_keys``
and writes a per-step cost, float ``[B, N, H]`` (lower is better), under its
``out_key`` (``"cost"`` by default), so costs compose like any TensorDict modules, best
in a :class:`CostSequence` (a ``TensorDictSequential`` that passes lazy values on)::

    CostSequence(
        PixelDistanceCost(out_key="pixel_cost"),
        CodeMatchCost(encoder, out_key="code_cost"),
        WeightedCostSum({"pixel_cost": 1.0, "code_cost": 0.5}),  # writes "cost"
    )

Lazy values
    A planning env may leave some predictions out of the rollout and hand them over
    lazily (its ``imagine_candidates``; the true dynamics give ``("next", "pixels")``
    as undrawn :class:`~dorp_rl.envs.planning.ImaginedFrames`). The planner then calls
    :func:`run_cost_lazy`: a cost declaring ``forward_lazy(rollout, lazy)`` gets them
    as they are, any other module gets those it reads materialised
    (:func:`materialize_lazy`). :class:`RolloutCost` declares it: its
    :meth:`~RolloutCost.per_step_cost_lazy` materialises what it reads and calls
    :meth:`~RolloutCost.per_step_cost`, and :class:`PixelDistanceCost` and
    :class:`CodeMatchCost` read imagined frames for less, with the same results. A
    subclass that redefines ``per_step_cost`` (or ``forward``) without its lazy
    counterpart gets the materialising default, so its override is what runs.

A cost also says, with its ``step_aggregation``, how a planner should fold the ``H``
per-step costs of one candidate into that candidate's score (it is not a loss
reduction: it decides which sequence is best and how much of it runs open loop):

- ``"min"``: the best step counts. A sequence is as good as the closest it gets to the
  goal; in open-loop execution the planner then executes the sequence only up to that
  step (the authors' release: "execute the prefix with the lowest pixel L2"). This is
  the default of :class:`PixelDistanceCost` and :class:`CodeMatchCost` (a sequence is
  good if it reaches the target code at some step).
- ``"sum"``: every step counts (the total along the way).
- ``"final"``: only the last step counts.

The planner uses ``in_keys`` (for a :class:`CostSequence` or any
:class:`~tensordict.nn.TensorDictSequential`, the keys read and not produced inside it) to stack only the predictions that are needed
and to check, before rolling out, that every key is there. A key missing from the
rollout raises :class:`MissingRolloutKeyError` (both a ``KeyError`` and a
``ValueError``) naming it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn

from dorp_rl.envs.planning import ImaginedFrames, distinct_rows, int64_columns, row_hashes
from dorp_rl.validation import check_float, check_int

__all__ = [
    "STEP_AGGREGATIONS",
    "CodeMatchCost",
    "CostSequence",
    "FirstArrival",
    "LatentGoalCost",
    "MissingRolloutKeyError",
    "NegativeRewardCost",
    "ObjectMapCost",
    "PixelDistanceCost",
    "RolloutCost",
    "WeightedCostSum",
    "check_step_aggregation",
    "materialize_lazy",
    "run_cost_lazy",
]

#: How a planner folds a candidate's per-step costs ``[H]`` into its score.
STEP_AGGREGATIONS = ("min", "sum", "final")


class MissingRolloutKeyError(KeyError, ValueError):
    """A key a cost needs is neither predicted by the planning env nor in the acting tensordict."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else ""


def get_rollout_key(rollout: TensorDictBase, key: NestedKey, cost_name: str) -> torch.Tensor:
    """``rollout.get(key)``, or a :class:`MissingRolloutKeyError` that names the key."""
    value = rollout.get(key, None)
    if value is None:
        available = sorted(str(k) for k in rollout.keys(True, True))
        hint = (
            "the planning env does not produce it"
            if isinstance(unravel_key(key), tuple) and unravel_key(key)[0] == "next"
            else "the tensordict given to the planner does not hold it"
        )
        raise MissingRolloutKeyError(
            f"{cost_name} needs the key {key!r}, which is missing from the imagined rollout "
            f"({hint}). Keys present: {available}."
        )
    return value


def check_step_aggregation(step_aggregation: str) -> str:
    """``step_aggregation`` if it is one of :data:`STEP_AGGREGATIONS`, else a ``ValueError``."""
    if step_aggregation not in STEP_AGGREGATIONS:
        raise ValueError(
            f"step_aggregation (how a candidate's per-step costs fold into its score) must be "
            f"one of {STEP_AGGREGATIONS}, got {step_aggregation!r}."
        )
    return step_aggregation


def compact_broadcast(tensor: torch.Tensor, keep_last: int) -> torch.Tensor:
    """Narrows every broadcast (stride-0) leading dimension to size 1.

    Root keys of a rollout are expanded views; converting one to float would otherwise
    materialise it ``N * H`` times. The result still broadcasts against the full shape.
    """
    for dim in range(tensor.dim() - keep_last):
        if tensor.stride(dim) == 0 and tensor.shape[dim] > 1:
            tensor = tensor.narrow(dim, 0, 1)
    return tensor


def materialize_lazy(
    rollout: TensorDictBase,
    lazy: Mapping[NestedKey, Any],
    keys: Sequence[NestedKey] | None = None,
) -> TensorDictBase:
    """Writes the ``lazy`` values (those of ``keys``; ``None``: all) into ``rollout``.

    Values the rollout already holds are left as they are; a lazy value is a tensor or a
    :class:`~dorp_rl.envs.planning.LazyValue` (its ``materialize()`` gives the tensor).
    Returns ``rollout``.
    """
    wanted = None if keys is None else {unravel_key(k) for k in keys}
    for key, value in lazy.items():
        key = unravel_key(key)
        if (wanted is not None and key not in wanted) or key in rollout.keys(True, True):
            continue
        rollout.set(key, value if isinstance(value, torch.Tensor) else value.materialize())
    return rollout


def lazy_frames(
    rollout: TensorDictBase, lazy: Mapping[NestedKey, Any], key: NestedKey
) -> ImaginedFrames | None:
    """``lazy[key]`` if it is :class:`~dorp_rl.envs.planning.ImaginedFrames` the rollout does
    not hold drawn (a cost may then read the states behind them), else ``None``."""
    frames = lazy.get(key)
    if not isinstance(frames, ImaginedFrames) or key in rollout.keys(True, True):
        return None
    return frames


def run_cost_lazy(
    cost: Callable, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
) -> TensorDictBase:
    """Runs ``cost`` on ``rollout`` whose ``lazy`` values are not materialised yet.

    A cost whose class declares ``forward_lazy(rollout, lazy)`` (:class:`RolloutCost`,
    :class:`CostSequence`) is handed the lazy values; any other module gets those it
    reads (its ``in_keys``; all of them when it declares none) materialised into the
    rollout and is called as usual. Without lazy values it is simply ``cost(rollout)``.
    Returns the rollout with the cost's outputs.
    """
    if not lazy:
        out = cost(rollout)
    elif callable(getattr(type(cost), "forward_lazy", None)):
        out = cost.forward_lazy(rollout, lazy)
    else:
        materialize_lazy(rollout, lazy, getattr(cost, "in_keys", None) or None)
        out = cost(rollout)
    return rollout if out is None else out


class RolloutCost(TensorDictModuleBase):
    """Base class of the costs: writes a per-step cost float ``[*B, N, H]`` under ``out_key``.

    Subclasses set ``in_keys`` (the keys they read) and implement
    :meth:`per_step_cost`; :meth:`forward` writes its result into the rollout and
    returns the rollout, as TensorDict modules do. Planners whose env leaves values
    lazy call :meth:`forward_lazy` (through :meth:`per_step_cost_lazy`), which by
    default materialises them; a subclass that redefines :meth:`per_step_cost` or
    :meth:`forward` without :meth:`per_step_cost_lazy` / :meth:`forward_lazy` gets that
    default back (``__init_subclass__``), so its own method is what runs.

    Args:
        out_key: where the per-step cost is written (``out_keys == [out_key]``).
        step_aggregation: how planners fold a candidate's per-step costs into its score
            (``"min"``, ``"sum"`` or ``"final"``, see the module docstring).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import RolloutCost
        >>> class StepsTaken(RolloutCost):
        ...     def __init__(self):
        ...         super().__init__(out_key="steps", step_aggregation="final")
        ...         self.in_keys = ["action"]
        ...
        ...     def per_step_cost(self, rollout):
        ...         return torch.arange(1.0, rollout.shape[-1] + 1).expand(rollout.shape)
        >>> actions = torch.zeros(2, 5, 3, 1, dtype=torch.int64)
        >>> rollout = TensorDict(action=actions, batch_size=(2, 5, 3))
        >>> StepsTaken()(rollout)["steps"][0, 0]
        tensor([1., 2., 3.])
    """

    def __init__(self, *, out_key: NestedKey = "cost", step_aggregation: str = "sum") -> None:
        super().__init__()
        self.out_key = unravel_key(out_key)
        self.in_keys = []
        self.out_keys = [self.out_key]
        self.step_aggregation = check_step_aggregation(step_aggregation)
        #: root keys the cost reads as frames (a goal image, the start frame): planners
        #: check them against the planning env once per call and hand them over as uint8
        self.root_frame_keys: list[NestedKey] = []

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        """The per-step cost, float ``[*B, N, H]``, of a rollout ``[*B, N, H]``."""
        raise NotImplementedError

    def forward(self, rollout: TensorDictBase) -> TensorDictBase:
        rollout.set(self.out_key, self.per_step_cost(rollout))
        return rollout

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        """:meth:`per_step_cost` of ``rollout`` completed by the ``lazy`` values.

        ``lazy`` maps rollout keys the planning env left out of ``rollout`` (e.g.
        ``("next", "pixels")``) to values computed on demand
        (:class:`~dorp_rl.envs.planning.LazyValue`, such as
        :class:`~dorp_rl.envs.planning.ImaginedFrames`). This default materialises the
        ones among :attr:`in_keys` into the rollout and calls :meth:`per_step_cost`; a
        cost that can read a lazy value for less (distinct frames only, distances from
        the states) overrides it, with exactly the same result.
        """
        materialize_lazy(rollout, lazy, self.in_keys)
        return self.per_step_cost(rollout)

    def forward_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> TensorDictBase:
        """:meth:`forward` through :meth:`per_step_cost_lazy`: what ``forward`` writes on
        the rollout with its lazy values materialised (see :func:`run_cost_lazy`)."""
        rollout.set(self.out_key, self.per_step_cost_lazy(rollout, lazy))
        return rollout

    def __init_subclass__(cls, **kwargs) -> None:
        # The contract: a class's lazy methods compute what its own per_step_cost /
        # forward compute. A subclass that redefines one of those without redefining its
        # lazy counterpart gets the default that materialises the lazy values and calls
        # the redefined method, so that its override is what runs.
        super().__init_subclass__(**kwargs)
        own = vars(cls)
        if "per_step_cost" in own and "per_step_cost_lazy" not in own:
            cls.per_step_cost_lazy = RolloutCost.per_step_cost_lazy
        if "forward" in own and "forward_lazy" not in own:
            cls.forward_lazy = _forward_materialized

    def extra_repr(self) -> str:
        return f"out_key={self.out_key!r}, step_aggregation={self.step_aggregation!r}"


def _forward_materialized(
    self: RolloutCost, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
) -> TensorDictBase:
    """``forward_lazy`` of a cost that redefines ``forward``: materialise, then call it."""
    materialize_lazy(rollout, lazy, self.in_keys or None)
    out = self(rollout)
    return rollout if out is None else out


#: Joins a frame's and a goal's row hashes into the key of the pair (an odd 64-bit factor).
_PAIR_KEY_FACTOR = 0x9E3779B97F4A7C15 - 2**64


class _GoalFrameCost(RolloutCost):
    """A cost of each predicted frame against the goal image (the shared keys and blurs)."""

    def _set_frame_keys(
        self,
        goal_key: NestedKey,
        pixels_key: NestedKey,
        chunk_size: int,
        blur_sigmas: Sequence[float],
        cache_size: int,
    ) -> None:
        self.chunk_size = check_int("chunk_size", chunk_size, low=1)
        self.blur_sigmas = _register_blurs(self, blur_sigmas)
        self.goal_key = unravel_key(goal_key)
        self.pixels_key = unravel_key(pixels_key)
        self.in_keys = [self.pixels_key, self.goal_key]
        self.root_frame_keys = [self.goal_key]
        self.cache = _KeyedCache(check_int("cache_size", cache_size, low=0))

    def _pair_costs(
        self,
        frames: torch.Tensor,
        goals: torch.Tensor,
        owner: torch.Tensor,
        compute: Callable[[torch.Tensor], torch.Tensor],
        module: nn.Module | None = None,
        cached: bool = True,
    ) -> torch.Tensor:
        """Costs ``[m]`` of the (frame, goal) pairs ``frames[i]``, ``goals[owner[i]]``:
        ``compute(indices)`` for the pairs not scored in an earlier call (the goal phase
        plans from nearly the same state many times), the others from the cache.
        ``cached=False`` computes them all: deduplication found two frames sharing a hash,
        which the cache, keyed by hashes, would confuse."""
        if (
            not cached
            or self.cache.size == 0
            or frames.dtype != torch.uint8
            or frames.shape[0] == 0
        ):
            return compute(torch.arange(frames.shape[0], device=frames.device))
        goal_keys = row_hashes(goals).index_select(0, owner)
        keys = row_hashes(frames) * _PAIR_KEY_FACTOR + goal_keys  # wraps modulo 2**64
        return self.cache.fetch(keys, lambda miss: (compute(miss),), module)[0]

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        return self._per_step_cost(rollout, None)

    def extra_repr(self) -> str:
        blur = f", blur_sigmas={self.blur_sigmas}" if self.blur_sigmas else ""
        return f"goal_key={self.goal_key!r}{blur}, {super().extra_repr()}"


class PixelDistanceCost(_GoalFrameCost):
    """L2 distance between each predicted frame and the goal image (the paper's VF cost).

    Per step: ``|| next_pixels / 255 - goal / 255 ||_2`` over the 768 values of the frame
    (0 when the predicted frame is the goal, about 4.9 for one 2x4 block of a saturated
    colour moved by one cell). ``step_aggregation="min"`` by default: a candidate is
    scored by the closest it gets to the goal.

    Plain L2 is flat once a block no longer overlaps its place in the goal image: moving
    it closer changes nothing until it touches. ``blur_sigmas`` adds the L2 distance of
    the frames blurred with a Gaussian of each given width (in cells), which keeps
    decreasing as a block approaches from further away.

    Args:
        goal_key: the goal image, uint8 ``[*B, C, H, W]`` in the acting tensordict.
        pixels_key: the predicted frames in the rollout.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per chunk of the computation (a speed knob, not a result one).
        blur_sigmas: widths of the extra blurred terms (default none: the paper's L2).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import PixelDistanceCost
        >>> goal = torch.zeros(2, 1, 1, 3, 16, 16, dtype=torch.uint8).expand(2, 5, 4, 3, 16, 16)
        >>> frames = torch.zeros(2, 5, 4, 3, 16, 16, dtype=torch.uint8)
        >>> rollout = TensorDict(
        ...     {"goal_pixels": goal, ("next", "pixels"): frames}, batch_size=(2, 5, 4)
        ... )
        >>> PixelDistanceCost()(rollout)["cost"].shape
        torch.Size([2, 5, 4])
    """

    def __init__(
        self,
        goal_key: NestedKey = "goal_pixels",
        pixels_key: NestedKey = ("next", "pixels"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
        chunk_size: int = 512,
        blur_sigmas: Sequence[float] = (),
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        self._set_frame_keys(goal_key, pixels_key, chunk_size, blur_sigmas, cache_size)

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        """The same costs from imagined states: exact distances without drawing frames.

        When the frames are lazy :class:`~dorp_rl.envs.planning.ImaginedFrames`: without
        ``blur_sigmas``, each squared distance is an integer below ``2**24`` (checked),
        which float32 holds exactly whatever the summation order, so it is computed in
        integers from the frames' parts; the blurred terms are computed on the distinct
        (frame, goal) pairs, of which only the distinct frames are drawn.
        """
        frames = lazy_frames(rollout, lazy, self.pixels_key)
        if frames is None:
            return super().per_step_cost_lazy(rollout, lazy)
        return self._per_step_cost(rollout, frames)

    def _per_step_cost(
        self, rollout: TensorDictBase, imagined: ImaginedFrames | None
    ) -> torch.Tensor:
        pairs = _GoalPairs(rollout, imagined, self.pixels_key, self.goal_key, type(self).__name__)
        goals = pairs.goals.reshape(pairs.goals.shape[0], -1).to(torch.float32)
        if imagined is not None and not self.blur_sigmas:
            goal_rows = pairs.goals.reshape(goals.shape)
            squared = imagined.squared_distances(goal_rows, pairs.owner)
            if squared is not None and (squared.numel() == 0 or int(squared.max()) < 2**24):
                # Exactly what the float loop below gives: every partial sum of the
                # squared differences is an integer below 2**24, which float32 holds.
                return squared.to(torch.float32).sqrt_().div_(255.0).reshape(pairs.lead)
        # Blurring costs ~50x the plain distance; imagined frames repeat a lot, so
        # score each distinct (frame, goal) pair once.
        frames, owner, inverse = pairs.distinct(dedupe=bool(self.blur_sigmas))
        frame_shape = pairs.frame_shape

        def compute(index: torch.Tensor) -> torch.Tensor:
            rows = frames.reshape(frames.shape[0], -1).index_select(0, index)
            out = torch.empty(rows.shape[0], dtype=torch.float32, device=rows.device)
            # Chunks of a few hundred frames stay in cache: ~10x faster than one pass.
            for start in range(0, rows.shape[0], self.chunk_size):
                stop = start + self.chunk_size
                diff = rows[start:stop].to(torch.float32)
                diff.sub_(goals.index_select(0, owner[index[start:stop]]))
                total = diff.square().sum(-1).sqrt_()
                for i in range(len(self.blur_sigmas)):
                    # Blurring is linear: the blurred frames differ by the blurred difference.
                    blurred = _blur(diff.view(-1, *frame_shape), getattr(self, f"_blur{i}"))
                    total += blurred.flatten(1).square().sum(-1).sqrt_()
                out[start:stop] = total
            return out

        if self.blur_sigmas:
            out = self._pair_costs(frames, pairs.goals, owner, compute, cached=inverse is not None)
        else:  # plain distances cost less than the cache's hashing
            out = compute(torch.arange(frames.shape[0], device=frames.device))
        if inverse is not None:
            out = out[inverse]
        return out.div_(255.0).reshape(pairs.lead)


def _blur(images: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of ``[n, c, h, w]`` images, mirrored at the borders.

    Mirroring (each border cell repeated once, then the image backwards) keeps every
    cell's mass inside the frame: with zero padding a block in a corner loses part of
    its blurred mass, so its distance to any far goal shrinks and pixel-distance
    planners drift into corners. The blur is linear, so it is two small matrix
    products, ``rows @ image @ cols.T``, with the mirroring folded into the matrices
    (several times faster than padded convolutions on 16 x 16 frames).
    """
    rows = _blur_matrix(taps, images.shape[-2]).to(images.dtype)
    cols = _blur_matrix(taps, images.shape[-1]).to(images.dtype)
    return torch.matmul(torch.matmul(rows, images), cols.transpose(0, 1))


def _blur_matrix(taps: torch.Tensor, size: int) -> torch.Tensor:
    """``[size, size]`` matrix of a 1-D blur with ``taps``, mirrored at both ends."""
    radius = taps.shape[0] // 2
    source = torch.arange(size, device=taps.device).unsqueeze(1) + torch.arange(
        -radius, radius + 1, device=taps.device
    )
    # Mirrored as often as needed (period 2 * size): a blur wider than a small frame
    # folds back into it and keeps all of its mass.
    source = source.remainder(2 * size)
    source = torch.where(source >= size, 2 * size - 1 - source, source)
    matrix = torch.zeros(size, size, dtype=taps.dtype, device=taps.device)
    return matrix.scatter_add_(1, source, taps.expand(size, -1).contiguous())


class _GoalPairs:
    """The (frame, goal) pairs of a rollout that a distance to the goal image scores.

    ``goals`` uint8 ``[G, *frame_shape]`` holds one copy per distinct goal (the goal is
    a broadcast view: it is never materialised ``N * H`` times) and ``owner [n]`` maps
    each of the ``n`` flat steps to its goal; ``lead`` is the rollout's ``[*B, N, H]``.
    """

    def __init__(
        self,
        rollout: TensorDictBase,
        imagined: ImaginedFrames | None,
        pixels_key: NestedKey,
        goal_key: NestedKey,
        name: str,
    ) -> None:
        self.imagined = imagined
        self.pixels = None
        if imagined is None:
            self.pixels = get_rollout_key(rollout, pixels_key, name)
            self.frame_shape, self.lead = self.pixels.shape[-3:], self.pixels.shape[:-3]
        else:
            self.frame_shape, self.lead = imagined.frame_shape, imagined.shape
        goal = get_rollout_key(rollout, goal_key, name)
        if tuple(self.frame_shape) != tuple(goal.shape[-3:]):
            raise ValueError(
                f"{goal_key!r} must have the frame shape of {pixels_key!r} "
                f"({list(self.frame_shape)}), got {list(goal.shape)}."
            )
        goal = compact_broadcast(goal.expand(*self.lead, *goal.shape[-3:]), keep_last=3)
        self.goals = goal.reshape(-1, *self.frame_shape)
        owner = torch.arange(self.goals.shape[0], device=goal.device).reshape(goal.shape[:-3])
        self.owner = owner.expand(self.lead).reshape(-1)

    def distinct(
        self, dedupe: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(frames [m, *frame_shape], owner [m], inverse [n] | None)``: with ``dedupe``,
        each distinct (frame, goal) pair once (imagined frames: only those are drawn),
        and ``inverse`` from every step to its pair (``None``: every step, in order)."""
        imagined, owner = self.imagined, self.owner
        if imagined is None:
            frames = self.pixels.reshape(-1, *self.frame_shape)
            if dedupe and frames.dtype == torch.uint8 and frames.shape[0] > 1:
                rows = frames.reshape(frames.shape[0], -1)
                owner_bytes = owner.unsqueeze(-1).contiguous().view(torch.uint8)
                pairs, inverse = distinct_rows(torch.cat([rows, owner_bytes], -1))
                if inverse is not None:
                    width = rows.shape[1]
                    frames = pairs[:, :width].reshape(-1, *self.frame_shape)
                    return (
                        frames,
                        int64_columns(pairs[:, width:]).squeeze(-1),
                        inverse,
                    )
            return frames, owner, None
        if dedupe and imagined.numel > 1:
            distinct, goal_index, inverse, _ = imagined.distinct(owner.unsqueeze(-1))
            return distinct, goal_index.squeeze(-1), inverse
        return imagined.pixels().reshape(-1, *self.frame_shape), owner, None


class LatentGoalCost(RolloutCost):
    """Distance of each imagined latent to the goal image's latent, in a latent world model.

    For planning envs that imagine latent states (:class:`~dorp_rl.envs.LatentModelEnv`
    writes ``("next", "latent")``): the goal image is encoded once per row by
    ``model.encode`` (the latent a real frame gets, which the model's dynamics are
    trained to reach) and each step costs the root mean square of the difference,
    ``|| latent - goal_latent ||_2 / sqrt(D)``. So the goal-image phase is judged in the
    model's own latent space, where a few pixels that matter (an agent's heading, say)
    are as visible as they are to the model's encoder, and no frame is decoded.

    Args:
        model: anything with ``encode(pixels [*B, C, H, W]) -> [*B, D]`` (a
            :class:`~dorp_rl.modules.LatentWorldModel`; a module is kept as a submodule).
        goal_key: the goal image, uint8 ``[*B, C, H, W]`` in the acting tensordict.
        latent_key: the imagined latents in the rollout, float ``[*B, N, H, D]``.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import LatentModelConfig, LatentWorldModel
        >>> from dorp_rl.planners import LatentGoalCost
        >>> model = LatentWorldModel(4, LatentModelConfig(frame_shape=(1, 8, 8), code_sizes=(4,)))
        >>> goal = torch.zeros(2, 1, 1, 1, 8, 8, dtype=torch.uint8).expand(2, 5, 3, 1, 8, 8)
        >>> latent = model.encode(torch.zeros(1, 8, 8, dtype=torch.uint8)).detach().expand(2, 5, 3, -1)
        >>> rollout = TensorDict({"goal_pixels": goal, ("next", "latent"): latent}, batch_size=(2, 5, 3))
        >>> cost = LatentGoalCost(model)(rollout)["cost"]
        >>> cost.shape, float(cost.abs().max()) < 1e-5  # every step is at the goal's latent
        (torch.Size([2, 5, 3]), True)
    """

    def __init__(
        self,
        model: Any,
        goal_key: NestedKey = "goal_pixels",
        latent_key: NestedKey = ("next", "latent"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(getattr(model, "encode", None)):
            raise ValueError(
                f"model must have encode(pixels) -> latents (a LatentWorldModel); "
                f"{type(model).__name__} has none."
            )
        self.model = model
        self.goal_key = unravel_key(goal_key)
        self.latent_key = unravel_key(latent_key)
        self.in_keys = [self.latent_key, self.goal_key]
        self.root_frame_keys = [self.goal_key]

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        name = type(self).__name__
        latent = get_rollout_key(rollout, self.latent_key, name)
        lead = latent.shape[:-1]
        goal = get_rollout_key(rollout, self.goal_key, name)
        frame = tuple(getattr(self.model, "frame_shape", goal.shape[-3:]))
        if goal.dim() != len(lead) + 3 or tuple(goal.shape[-3:]) != frame:
            raise ValueError(
                f"{self.goal_key!r} must be frames {list(frame)} over the rollout's "
                f"{list(lead)}, got {list(goal.shape)}."
            )
        # The goal is a broadcast view: encode each distinct row's goal once.
        goal = compact_broadcast(goal.expand(*lead, *frame), keep_last=3)
        with torch.no_grad():
            target = self.model.encode(goal)  # [*compact lead, D]
        if target.shape[-1] != latent.shape[-1]:
            raise ValueError(
                f"the goal's latent has width {target.shape[-1]} but {self.latent_key!r} has "
                f"{latent.shape[-1]}: the model is not the planning env's."
            )
        diff = latent.to(torch.float32) - target.to(torch.float32)
        return diff.square().mean(-1).sqrt()

    def extra_repr(self) -> str:
        return f"goal_key={self.goal_key!r}, latent_key={self.latent_key!r}, {super().extra_repr()}"


class ObjectMapCost(_GoalFrameCost):
    """Distance of each object's map in the predicted frames to its map in the goal image.

    The encoder's object extractor gives one map per one-hot (``encoder.object_maps``,
    float ``[*B, K, H, W]``; with DORP's codes, one object each). Per step::

        sum_k ( ||m_k - g_k||_2 + sum_s ||blur_s(m_k - g_k)||_2 )

    over the maps ``m_k`` of the predicted frame and ``g_k`` of the goal image. Each
    object has its own term, so moving one object towards its goal place never pays for
    another: pixel distance trades objects off (two blocks each in the other's goal place
    are a local minimum for it, since a block stepping aside first makes the frame differ
    from the goal in more cells), object maps do not. The goal-image phase of
    :class:`~dorp_rl.policies.AbstractGoalPolicy` adds it to the pixel distance.

    Args:
        encoder: anything with ``object_maps(pixels) -> [*B, K, H, W]``
            (:class:`~dorp_rl.modules.DiscreteCodeEncoder`); run in eval mode without
            gradients, its mode restored after.
        goal_key: the goal image in the acting tensordict.
        pixels_key: the predicted frames in the rollout.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per encoder call (bounds memory).
        blur_sigmas: widths of the blurred terms, in cells (as :class:`PixelDistanceCost`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import ObjectMapCost
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> goal = frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16)
        >>> rollout = TensorDict(
        ...     {"goal_pixels": goal, ("next", "pixels"): frames}, batch_size=(2, 5, 4)
        ... )
        >>> cost = ObjectMapCost(encoder, blur_sigmas=(2.0,))(rollout)["cost"]
        >>> cost.shape, float(cost[0, 0, 0])
        (torch.Size([2, 5, 4]), 0.0)
    """

    def __init__(
        self,
        encoder: nn.Module,
        goal_key: NestedKey = "goal_pixels",
        pixels_key: NestedKey = ("next", "pixels"),
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "min",
        chunk_size: int = 1024,
        blur_sigmas: Sequence[float] = (),
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(getattr(encoder, "object_maps", None)):
            raise ValueError(
                f"ObjectMapCost needs an encoder with object_maps(pixels) -> [*B, K, H, W] "
                f"(a DiscreteCodeEncoder), got {type(encoder).__name__}, which has none."
            )
        self.encoder = encoder
        self._set_frame_keys(goal_key, pixels_key, chunk_size, blur_sigmas, cache_size)

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        """The same costs, drawing and mapping distinct (frame, goal) pairs only."""
        frames = lazy_frames(rollout, lazy, self.pixels_key)
        if frames is None:
            return super().per_step_cost_lazy(rollout, lazy)
        return self._per_step_cost(rollout, frames)

    @torch.no_grad()
    def _maps(self, frames: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.encoder.object_maps(c) for c in frames.split(self.chunk_size)])

    @torch.no_grad()
    def _per_step_cost(
        self, rollout: TensorDictBase, imagined: ImaginedFrames | None
    ) -> torch.Tensor:
        pairs = _GoalPairs(rollout, imagined, self.pixels_key, self.goal_key, type(self).__name__)
        frames, owner, inverse = pairs.distinct()
        module = self.encoder if isinstance(self.encoder, nn.Module) else None
        was_training = module.training if module is not None else False
        if module is not None:
            module.eval()
        try:
            goal_maps = self._maps(pairs.goals).to(torch.float32)

            def compute(index: torch.Tensor) -> torch.Tensor:
                out = torch.empty(index.shape[0], dtype=torch.float32, device=goal_maps.device)
                for start in range(0, index.shape[0], self.chunk_size):
                    chunk = index[start : start + self.chunk_size]
                    diff = self._maps(frames.index_select(0, chunk)).to(torch.float32)
                    diff.sub_(goal_maps.index_select(0, owner.index_select(0, chunk)))
                    total = diff.flatten(2).square().sum(-1).sqrt_().sum(-1)
                    for i in range(len(self.blur_sigmas)):
                        blurred = _blur(diff, getattr(self, f"_blur{i}"))
                        total += blurred.flatten(2).square().sum(-1).sqrt_().sum(-1)
                    out[start : start + chunk.shape[0]] = total
                return out

            out = self._pair_costs(
                frames, pairs.goals, owner, compute, module, cached=inverse is not None
            )
        finally:
            if module is not None:
                module.train(was_training)
        if inverse is not None:
            out = out[inverse]
        return out.reshape(pairs.lead)


def _register_blurs(module: nn.Module, blur_sigmas: Sequence[float]) -> tuple[float, ...]:
    """Checks ``blur_sigmas`` and registers the Gaussian taps of each as ``_blur{i}``."""
    if isinstance(blur_sigmas, (str, bytes)) or not isinstance(blur_sigmas, Sequence):
        raise ValueError(f"blur_sigmas must be a sequence of positive widths, got {blur_sigmas!r}.")
    sigmas = [
        check_float(f"blur_sigmas[{i}]", x, low=0.0, low_open=True)
        for i, x in enumerate(blur_sigmas)
    ]
    for i, sigma in enumerate(sigmas):
        radius = min(15, math.ceil(3 * sigma))
        taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1) / sigma) ** 2)
        module.register_buffer(f"_blur{i}", taps / taps.sum(), persistent=False)
    return tuple(sigmas)


class _KeyedCache:
    """Values of rows already computed, keyed by a 64-bit hash of the rows' bytes.

    Planning calls keep imagining the same few thousand frames around the current state,
    so most model, encoder and cost calls repeat earlier ones. Each entry is a tuple of
    tensor rows (codes and probabilities of a frame; the cost of a (frame, goal) pair).
    Entries are appended to fixed storage of ``size`` rows; a sorted index of their keys
    (looked up with ``searchsorted``) is all that is re-sorted per call, so an insertion
    costs 16 bytes per held entry rather than a copy of every held value. When the
    storage is full the cache starts afresh. It is emptied whenever the weights of the
    module computing the values change (their ``_version`` counters, which every in-place
    update such as an optimiser step increments) and is not part of any state dict. Rows
    are matched by their :func:`~dorp_rl.envs.planning.row_hashes`: two different rows
    share one with probability at most about 2**-56 per pair, and rows found sharing one
    while deduplicating a call are not cached.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.keys = self.slots = None  # sorted keys [n] and their storage rows [n]
        self.values: tuple[torch.Tensor, ...] | None = None  # storage [size, ...] each
        self.count = 0
        self.version: tuple | None = None

    def clear(self) -> None:
        """Forget every entry (the storage is kept for reuse)."""
        self.keys = self.slots = None
        self.count = 0

    def fetch(
        self,
        keys: torch.Tensor,
        compute: Callable[[torch.Tensor], tuple[torch.Tensor, ...]],
        module: nn.Module | None,
    ) -> tuple[torch.Tensor, ...]:
        """The values of the rows of ``keys`` (int64 ``[n]``): held ones from the cache,
        the others from ``compute(indices)`` (the indices into ``keys`` it misses), which
        are then held too."""
        count = keys.shape[0]
        version = (id(module), *(p._version for p in module.parameters())) if module else None
        if version != self.version:
            self.clear()
            self.version = version
        hit = torch.zeros(count, dtype=torch.bool, device=keys.device)
        slot = None
        if self.keys is not None and self.keys.device == keys.device:
            pos = torch.searchsorted(self.keys, keys).clamp_max(self.keys.shape[0] - 1)
            hit = self.keys[pos] == keys
            slot = self.slots[pos]
        miss = (~hit).nonzero().squeeze(-1)
        new = compute(miss) if miss.numel() else None
        if slot is None:
            out = tuple(
                torch.empty(count, *v.shape[1:], dtype=v.dtype, device=v.device) for v in new
            )
        else:
            slot = slot.masked_fill(~hit, 0)
            out = tuple(stored[slot] for stored in self.values)
        if new is not None:
            for target, value in zip(out, new, strict=True):
                target[miss] = value
            self._insert(keys[miss], new)
        return out

    def _insert(self, keys: torch.Tensor, values: tuple[torch.Tensor, ...]) -> None:
        added = keys.shape[0]
        if added > self.size:
            return
        if self.count + added > self.size:
            self.clear()
        if self.values is None or any(
            stored.shape[1:] != v.shape[1:] or stored.dtype != v.dtype or stored.device != v.device
            for stored, v in zip(self.values, values, strict=True)
        ):
            self.clear()
            self.values = tuple(v.new_empty(self.size, *v.shape[1:]) for v in values)
        rows = torch.arange(self.count, self.count + added, device=keys.device)
        for stored, value in zip(self.values, values, strict=True):
            stored[rows] = value
        self.count += added
        if self.keys is not None:
            keys, rows = torch.cat([self.keys, keys]), torch.cat([self.slots, rows])
        order = torch.argsort(keys)
        self.keys, self.slots = keys[order], rows[order]


class _EncodingCache(_KeyedCache):
    """Codes and probabilities of frames already encoded (a :class:`_KeyedCache` of frames)."""

    def encode(self, frames, encode_frames, module: nn.Module | None, keys=None):
        """Codes and probabilities of ``frames``; ``keys``: their row hashes if known.

        ``frames`` may also be a function drawing the uint8 frames of given indices
        (``None``: all), with ``keys`` given: only the frames the cache misses are drawn.
        """
        lazy = not isinstance(frames, torch.Tensor)
        if lazy and (keys is None or self.size == 0):
            frames, lazy = frames(None), False
        if not lazy and (self.size == 0 or frames.dtype != torch.uint8 or frames.shape[0] == 0):
            return encode_frames(frames)
        keys = row_hashes(frames) if keys is None else keys
        return self.fetch(
            keys, lambda miss: encode_frames(frames(miss) if lazy else frames[miss]), module
        )


#: ``step_penalty`` of :class:`CodeMatchCost` stays below this, so that a match at step 25
#: still costs less than 0.5 (less than a frame that misses the code)
STEP_PENALTY_MAX = 0.02


def check_step_penalty(value: float, name: str = "step_penalty") -> float:
    """``value`` as a finite float in ``[0, STEP_PENALTY_MAX)``, or a ``ValueError`` naming ``name``."""
    try:
        return check_float(name, value, low=0.0, high=STEP_PENALTY_MAX, high_open=True)
    except ValueError as err:
        raise ValueError(f"{err} (so that a match at step 25 still costs less than 0.5)") from None


class CodeMatchCost(RolloutCost):
    """0 once the encoder's code of a predicted frame is the target code, else 1.

    DORP's waypoint cost. At each step the predicted frame is encoded; the step
    *matches* when the chosen one-hots hold the target code (``target_key``, e.g.
    ``subgoal_code``) while every other one-hot keeps its code of the start frame (root
    ``pixels``: the frame the planner started from). Per-step cost::

        (step_penalty * t if match else 1) - tie_break * confidence

    where ``confidence`` is the mean over one-hots of the probability of the wanted code,
    so that among matching sequences (and among failing ones) the more confident win,
    and ``t`` is the step (1..H): with ``step_penalty > tie_break`` a sequence that
    reaches the target earlier wins over one that gets there later, whatever their
    confidence (``"min"`` alone scores both alike, so plans took detours). The cost lies
    in ``[-tie_break, 1]``. ``step_aggregation="min"`` by default: a
    sequence is good if it reaches the target at some step (and open-loop execution
    stops there).

    Args:
        encoder: a :class:`~dorp_rl.modules.DiscreteCodeEncoder` (anything with
            ``encoder(pixels) -> (code [*B, C], probs [*B, C, Z])`` works). It is run in
            eval mode without gradients and its mode is restored after.
        target_key: target code, int64 ``[*B, C]`` in the acting tensordict.
        onehots: which one-hots must reach the target: ``None`` for all of them, a
            sequence of indices, or a key of a bool ``[*B, C]`` mask in the acting
            tensordict (one choice per row, as a batched DORP policy needs).
        pixels_key: the predicted frames in the rollout.
        start_pixels_key: the start frame (a root key, shared by candidates and steps).
        code_key: the predicted codes in the rollout, int64 ``[*B, N, H, C]``, when the
            planning env writes them (a latent world model's code head,
            :class:`~dorp_rl.envs.LatentModelEnv`): then no predicted frame is read or
            encoded (only the start frame, once per row) and there is no confidence
            term. ``None`` (default): the frames under ``pixels_key`` are encoded.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        tie_break: weight of the confidence term; small so it only breaks ties.
        step_penalty: cost per step of a matching frame (e.g. ``2 * tie_break``), so
            that earlier arrival wins; 0 (default) scores every matching step alike
            (docs/NOTES.md has what it did to DORP's steps and success).
        step_aggregation: how planners fold the steps (``"min"``, ``"sum"`` or ``"final"``).
        chunk_size: frames per encoder call (bounds memory).
        cache_size: frames whose codes are kept between calls (0: no cache). The
            cache is emptied whenever the encoder's weights change.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import CodeMatchCost
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> rollout = TensorDict(
        ...     {
        ...         "pixels": frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16),
        ...         "subgoal_code": torch.zeros(2, 1, 1, 2, dtype=torch.int64).expand(2, 5, 4, 2),
        ...         ("next", "pixels"): frames,
        ...     },
        ...     batch_size=(2, 5, 4),
        ... )
        >>> cost = CodeMatchCost(encoder, onehots=[0])(rollout)["cost"]
        >>> cost.shape, bool(((cost > -0.01) & (cost <= 1)).all())
        (torch.Size([2, 5, 4]), True)
    """

    def __init__(
        self,
        encoder: nn.Module,
        target_key: NestedKey = "subgoal_code",
        onehots: Sequence[int] | NestedKey | None = None,
        *,
        pixels_key: NestedKey = ("next", "pixels"),
        start_pixels_key: NestedKey = "pixels",
        code_key: NestedKey | None = None,
        out_key: NestedKey = "cost",
        tie_break: float = 1e-3,
        step_penalty: float = 0.0,
        step_aggregation: str = "min",
        chunk_size: int = 1024,
        cache_size: int = 2**18,
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not callable(encoder):
            raise ValueError(f"encoder must be callable, got {type(encoder).__name__}.")
        cache_size = check_int("cache_size", cache_size, low=0)
        self.cache = _EncodingCache(cache_size)
        self.tie_break = check_float("tie_break", tie_break, low=0.0, high=0.5, high_open=True)
        chunk_size = check_int("chunk_size", chunk_size, low=1)
        self.encoder = encoder
        self.target_key = unravel_key(target_key)
        self.pixels_key = unravel_key(pixels_key)
        self.start_pixels_key = unravel_key(start_pixels_key)
        self.code_key = None if code_key is None else unravel_key(code_key)
        step_penalty = check_step_penalty(step_penalty)
        self.step_penalty = step_penalty
        self.chunk_size = int(chunk_size)
        self.onehots_key: NestedKey | None = None
        self.onehots: list[int] | None = None
        # A key is a string or a tuple of strings (nested); anything else is indices.
        if isinstance(onehots, str) or (
            isinstance(onehots, tuple) and onehots and all(isinstance(i, str) for i in onehots)
        ):
            self.onehots_key = unravel_key(onehots)
        elif onehots is not None:
            self.onehots = self._check_onehots(onehots, encoder)
        predicted = self.pixels_key if self.code_key is None else self.code_key
        in_keys = [predicted, self.start_pixels_key, self.target_key]
        if self.onehots_key is not None:
            in_keys.append(self.onehots_key)
        self.in_keys = in_keys
        self.root_frame_keys = [self.start_pixels_key]

    @staticmethod
    def _check_onehots(onehots: Sequence[int], encoder: nn.Module) -> list[int]:
        """``onehots`` as distinct indices of the encoder's one-hots (its ``code_sizes``)."""
        if isinstance(onehots, (str, bytes)) or not isinstance(onehots, Sequence):
            raise ValueError(
                f"onehots must be None, a sequence of one-hot indices or a mask key, got "
                f"{onehots!r}."
            )
        sizes = getattr(encoder, "code_sizes", None)
        count = len(sizes) if sizes is not None else None
        high = None if count is None else count - 1
        chosen = [check_int(f"onehots[{i}]", v, low=0) for i, v in enumerate(onehots)]
        if not chosen:
            raise ValueError("onehots must name at least one one-hot (or be None for all).")
        if high is not None and any(i > high for i in chosen):
            raise ValueError(
                f"onehots must be indices of the encoder's {count} one-hot(s) (0 to {high}, "
                f"code_sizes {tuple(sizes)}), got {tuple(onehots)}."
            )
        if len(set(chosen)) != len(chosen):
            raise ValueError(f"onehots must name each one-hot once, got {tuple(onehots)}.")
        return chosen

    @torch.no_grad()
    def _encode(
        self, pixels: torch.Tensor | None, imagined: ImaginedFrames | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Codes ``[*S, C]`` and probabilities ``[*S, C, Z]`` of frames ``[*S, *frame_shape]``.

        The frames are ``pixels``, or ``imagined`` (of which only distinct ones that the
        cache does not hold are drawn).
        """
        code, prob, inverse = self._encode_distinct(pixels, imagined)
        if inverse is not None:
            code, prob = code[inverse], prob[inverse]
        lead = pixels.shape[:-3] if imagined is None else imagined.shape
        return code.reshape(*lead, code.shape[-1]), prob.reshape(*lead, *prob.shape[-2:])

    @torch.no_grad()
    def _encode_distinct(
        self, pixels: torch.Tensor | None, imagined: ImaginedFrames | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Codes ``[m, C]`` and probabilities ``[m, C, Z]`` of the distinct frames, and the
        ``inverse [n]`` from every flat frame to its distinct one (``None``: ``m = n``)."""
        module = self.encoder if isinstance(self.encoder, nn.Module) else None
        was_training = module.training if module is not None else False
        if module is not None:
            module.eval()
        try:
            inverse = keys = None
            if imagined is not None and imagined.numel > 1:
                flat, _, inverse, keys = imagined.distinct(draw=False)
            else:
                if imagined is not None:
                    pixels = imagined.pixels()
                flat = pixels.reshape(-1, *pixels.shape[-3:])
                if flat.dtype == torch.uint8 and flat.shape[0] > 1:
                    # Imagined frames repeat a lot, within a call and across calls: encode
                    # each distinct frame once, and frames seen in earlier calls not at all.
                    flat, inverse = distinct_rows(flat)
            if inverse is None and not callable(flat) and flat.shape[0] > 1:
                # deduplication found two frames sharing a hash: keep them out of the
                # cache, which is keyed by hashes
                code, prob = self._encode_frames(flat)
            else:
                code, prob = self.cache.encode(flat, self._encode_frames, module, keys=keys)
        finally:
            if module is not None:
                module.train(was_training)
        return code, prob, inverse

    def _encode_frames(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codes, probs = [], []
        for chunk in frames.split(self.chunk_size):
            code, prob = self.encoder(chunk)
            codes.append(code)
            probs.append(prob)
        return torch.cat(codes), torch.cat(probs)

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        return self._per_step_cost(rollout, None)

    def per_step_cost_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> torch.Tensor:
        """The same costs from lazy :class:`~dorp_rl.envs.planning.ImaginedFrames`,
        drawing and encoding distinct frames only."""
        frames = lazy_frames(rollout, lazy, self.pixels_key)
        if frames is None:
            return super().per_step_cost_lazy(rollout, lazy)
        return self._per_step_cost(rollout, frames)

    def _per_step_cost(
        self, rollout: TensorDictBase, imagined: ImaginedFrames | None
    ) -> torch.Tensor:
        name = type(self).__name__
        if rollout.batch_dims < 2:
            raise ValueError(
                f"{name} needs a rollout of batch shape [*B, N, H], got {list(rollout.batch_size)}."
            )
        if self.code_key is not None:
            return self._cost_of_predicted_codes(rollout)
        predicted = (
            None if imagined is not None else get_rollout_key(rollout, self.pixels_key, name)
        )
        start = get_rollout_key(rollout, self.start_pixels_key, name)
        target = get_rollout_key(rollout, self.target_key, name)
        if target.dtype.is_floating_point or target.dtype == torch.bool:
            raise ValueError(f"{self.target_key!r} must hold integer codes, got {target.dtype}.")
        # All candidates and steps share the start frame: encode it once per row.
        start_code = self._encode(start[..., :1, :1, :, :, :])[0]  # [*B, 1, 1, C]
        inverse = None
        if imagined is None:
            code, probs = self._encode(predicted)  # [*B, N, H, C], [*B, N, H, C, Z]
        else:
            # Codes and probabilities of the distinct frames, [m, C] and [m, C, Z]: the
            # [*B, N, H, C, Z] probabilities are never materialised (see below).
            code, probs, inverse = self._encode_distinct(None, imagined)
            if inverse is None:
                lead = imagined.shape
                code = code.reshape(*lead, code.shape[-1])
                probs = probs.reshape(*lead, *probs.shape[-2:])
            else:
                distinct_probs = probs
                code = code[inverse].reshape(*imagined.shape, code.shape[-1])
        num_onehots = code.shape[-1]
        if target.shape[-1] != num_onehots:
            raise ValueError(
                f"{self.target_key!r} must have {num_onehots} codes (one per one-hot), "
                f"got shape {list(target.shape)}."
            )
        chosen = self._chosen(rollout, num_onehots, code.device)
        self._check_target(target, chosen, probs.shape[-1])
        wanted = torch.where(chosen, target.to(code.device), start_code)  # [*B, N, H, C]
        num_codes = probs.shape[-1]
        if inverse is not None and bool(((wanted < 0) | (wanted >= num_codes)).any()):
            # Out-of-range codes: let gather refuse them as on the drawn path.
            probs = distinct_probs[inverse].reshape(*code.shape, num_codes)
            inverse = None
        wanted = wanted.expand_as(code)
        match = (code == wanted).all(-1)
        if inverse is None:
            picked = probs.gather(-1, wanted.unsqueeze(-1)).squeeze(-1)
        else:
            # The same entries as gathering from distinct_probs[inverse], read in place.
            flat_wanted = wanted.reshape(-1, num_onehots)
            onehot = torch.arange(num_onehots, device=code.device)
            index = (inverse.unsqueeze(-1) * num_onehots + onehot) * num_codes + flat_wanted
            picked = distinct_probs.reshape(-1)[index].reshape(code.shape)
        confidence = picked.mean(-1)
        cost = (~match).to(torch.float32) - self.tie_break * confidence.to(torch.float32)
        if self.step_penalty:
            steps = torch.arange(1, cost.shape[-1] + 1, device=cost.device, dtype=cost.dtype)
            cost = cost + self.step_penalty * steps * match.to(cost.dtype)
        return cost

    def _chosen(self, rollout: TensorDictBase, num_onehots: int, device: Any) -> torch.Tensor:
        """Bool mask of the one-hots that must reach the target (per row, or fixed)."""
        if self.onehots_key is not None:
            name = type(self).__name__
            return get_rollout_key(rollout, self.onehots_key, name).to(torch.bool)
        chosen = torch.zeros(num_onehots, dtype=torch.bool, device=device)
        chosen[self.onehots if self.onehots is not None else slice(None)] = True
        return chosen

    def _cost_of_predicted_codes(self, rollout: TensorDictBase) -> torch.Tensor:
        """Per-step costs from the codes the planning env predicted (``code_key``)."""
        name = type(self).__name__
        code = get_rollout_key(rollout, self.code_key, name)
        start = get_rollout_key(rollout, self.start_pixels_key, name)
        target = get_rollout_key(rollout, self.target_key, name)
        if code.dtype.is_floating_point or target.dtype.is_floating_point:
            raise ValueError(
                f"{self.code_key!r} and {self.target_key!r} must hold integer codes, got "
                f"{code.dtype} and {target.dtype}."
            )
        start_code = self._encode(start[..., :1, :1, :, :, :])[0]  # [*B, 1, 1, C]
        num_onehots = code.shape[-1]
        if target.shape[-1] != num_onehots or start_code.shape[-1] != num_onehots:
            raise ValueError(
                f"the planning env predicts {num_onehots} codes per frame under "
                f"{self.code_key!r}; the encoder gives {start_code.shape[-1]} and "
                f"{self.target_key!r} holds {target.shape[-1]}: the world model was trained "
                "on another encoder's codes."
            )
        chosen = self._chosen(rollout, num_onehots, code.device)
        wanted = torch.where(chosen, target.to(code.device), start_code.to(code.device))
        match = (code == wanted.expand_as(code)).all(-1)
        cost = (~match).to(torch.float32)
        if self.step_penalty:
            steps = torch.arange(1, cost.shape[-1] + 1, device=cost.device, dtype=cost.dtype)
            cost = cost + self.step_penalty * steps * match.to(cost.dtype)
        return cost

    def _check_target(self, target: torch.Tensor, chosen: torch.Tensor, max_codes: int) -> None:
        """Refuses a target code outside its one-hot's codes (on the broadcast rows only)."""
        sizes = getattr(self.encoder, "code_sizes", None) or (max_codes,) * target.shape[-1]
        sizes = torch.as_tensor(sizes, device=target.device)
        chosen = compact_broadcast(chosen.to(target.device).expand_as(target), keep_last=1)
        target = compact_broadcast(target, keep_last=1)
        bad = ((target < 0) | (target >= sizes)) & chosen
        target = target.expand_as(bad)
        if bad.any():
            index = bad.nonzero()[0].tolist()
            onehot = index[-1]
            raise ValueError(
                f"{self.target_key!r} holds code {int(target[tuple(index)])} for one-hot "
                f"{onehot}, which has {int(sizes[onehot])} codes (valid: 0 to "
                f"{int(sizes[onehot]) - 1})."
            )

    def extra_repr(self) -> str:
        which = self.onehots_key if self.onehots_key is not None else self.onehots
        return f"target_key={self.target_key!r}, onehots={which!r}, {super().extra_repr()}"


class CostSequence(TensorDictSequential):
    """A :class:`~tensordict.nn.TensorDictSequential` of costs that passes lazy values on.

    Called on a rollout it is the plain sequence: each cost in turn, in the order given.
    A planner whose env leaves some predictions lazy (``("next", "pixels")`` of
    :class:`~dorp_rl.envs.GroundTruthModelEnv` as undrawn
    :class:`~dorp_rl.envs.planning.ImaginedFrames`) calls :meth:`forward_lazy`
    instead, which hands those values to every member through :func:`run_cost_lazy`:
    costs that read them lazily do, the others get them materialised. A plain
    ``TensorDictSequential`` works with the planners too, with every lazy value it
    reads materialised first. The costs are given in order (``CostSequence(a, b, c)``
    or one list), not as a mapping.

    Examples:
        >>> from dorp_rl.planners import CostSequence, PixelDistanceCost, WeightedCostSum
        >>> cost = CostSequence(
        ...     PixelDistanceCost(out_key="near"),
        ...     PixelDistanceCost(out_key="blurred", blur_sigmas=(2.0,)),
        ...     WeightedCostSum({"near": 1.0, "blurred": 0.5}),
        ... )
        >>> cost.in_keys, cost.out_keys[-1]
        ([('next', 'pixels'), 'goal_pixels'], 'cost')
    """

    def __init__(self, *costs: Callable) -> None:
        if len(costs) == 1 and isinstance(costs[0], Mapping):
            raise ValueError(
                "CostSequence takes its costs in order, CostSequence(cost_a, cost_b, ...), "
                "not as a mapping of names."
            )
        super().__init__(*costs)

    def forward(self, rollout: TensorDictBase, *args: Any, **kwargs: Any) -> TensorDictBase:
        if args or kwargs:
            return super().forward(rollout, *args, **kwargs)
        return self.forward_lazy(rollout, {})

    def forward_lazy(
        self, rollout: TensorDictBase, lazy: Mapping[NestedKey, Any]
    ) -> TensorDictBase:
        """Runs the costs in order on ``rollout``, handing each the ``lazy`` values.

        A term that only the last member (a :class:`WeightedCostSum`) reads, weighted by
        a per-row weight that is 0 in every row, is not computed: it is written as zeros
        (the goal phase's code term once every row dropped it).
        """
        unread = self._terms_read_by_sum_only()
        for index in range(len(self)):
            member = self[index]
            weight_key = unread.get(index)
            if weight_key is not None:
                weight = rollout.get(weight_key, None)
                if weight is not None and not weight.any():
                    shape = rollout.batch_size
                    rollout.set(member.out_key, torch.zeros(shape, device=weight.device))
                    continue
            rollout = run_cost_lazy(member, rollout, lazy)
        return rollout

    def _terms_read_by_sum_only(self) -> dict[int, NestedKey]:
        """Index of each cost whose one output only a final :class:`WeightedCostSum`
        reads, weighted by a per-row key -> that key."""
        total = self[len(self) - 1]
        if not isinstance(total, WeightedCostSum):
            return {}
        out: dict[int, NestedKey] = {}
        for index in range(len(self) - 1):
            member = self[index]
            if not isinstance(member, RolloutCost) or len(member.out_keys) != 1:
                continue
            weight = total.weights.get(member.out_key)
            if weight is None or isinstance(weight, float):
                continue
            readers = [m for m in list(self)[index + 1 : -1] if member.out_key in m.in_keys]
            if not readers:
                out[index] = weight
        return out


class WeightedCostSum(RolloutCost):
    """Writes ``sum_k weights[k] * rollout[k]``: a weighted sum of per-step costs.

    The last module of a :class:`CostSequence` (or any
    :class:`~tensordict.nn.TensorDictSequential`) of costs, each writing its per-step
    cost under its own ``out_key``. The sequence's ``in_keys`` are
    the keys its costs read from the rollout (not the intermediate cost keys), which is
    what a planner needs; its last out key (this module's ``out_key``) is the one the
    planner reads by default. A sequence has no ``step_aggregation`` attribute, so pass
    ``step_aggregation=`` to the planner unless ``"sum"`` is wanted.

    Args:
        weights: per-step cost key -> weight: a number, or the key of a per-row weight
            (``[*B, 1]`` in the acting tensordict, carried into the rollout), so a policy
            can turn a term up or down for one env without another cost module.
        out_key: where the weighted sum ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (default ``"sum"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
        >>> from dorp_rl.planners import (
        ...     CodeMatchCost, CostSequence, PixelDistanceCost, WeightedCostSum
        ... )
        >>> encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
        >>> cost = CostSequence(
        ...     PixelDistanceCost(out_key="pixel_cost"),
        ...     CodeMatchCost(encoder, out_key="code_cost"),
        ...     WeightedCostSum({"pixel_cost": 1.0, "code_cost": 0.5}),
        ... )
        >>> cost.in_keys
        [('next', 'pixels'), 'goal_pixels', 'pixels', 'subgoal_code']
        >>> cost.out_keys
        ['pixel_cost', 'code_cost', 'cost']
        >>> frames = torch.randint(0, 256, (2, 5, 4, 3, 16, 16), dtype=torch.uint8)
        >>> start = frames[:, :1, :1].expand(2, 5, 4, 3, 16, 16)
        >>> rollout = TensorDict(
        ...     {
        ...         "pixels": start,
        ...         "goal_pixels": start,
        ...         "subgoal_code": torch.zeros(2, 1, 1, 2, dtype=torch.int64).expand(2, 5, 4, 2),
        ...         ("next", "pixels"): frames,
        ...     },
        ...     batch_size=(2, 5, 4),
        ... )
        >>> out = cost(rollout)
        >>> torch.allclose(out["cost"], out["pixel_cost"] + 0.5 * out["code_cost"])
        True
    """

    def __init__(
        self,
        weights: Mapping[NestedKey, float | NestedKey],
        *,
        out_key: NestedKey = "cost",
        step_aggregation: str = "sum",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        if not isinstance(weights, Mapping) or not weights:
            raise ValueError(
                f"weights must be a non-empty mapping from per-step cost keys to weights, "
                f"got {weights!r}."
            )
        self.weights: dict[NestedKey, float | NestedKey] = {}
        for key, weight in weights.items():
            key = unravel_key(key)
            if key in self.weights:
                raise ValueError(f"weights names the key {key!r} twice.")
            if isinstance(weight, (str, tuple)):
                self.weights[key] = unravel_key(weight)
                continue
            if (
                isinstance(weight, bool)
                or not isinstance(weight, (int, float))
                or not math.isfinite(float(weight))
            ):
                raise ValueError(
                    f"the weight of {key!r} must be a finite number or the key of a per-row "
                    f"weight, got {weight!r}."
                )
            self.weights[key] = float(weight)
        weight_keys = [w for w in self.weights.values() if not isinstance(w, float)]
        self.in_keys = list(dict.fromkeys([*self.weights, *weight_keys]))

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        name = type(self).__name__
        total = None
        for key, weight in self.weights.items():
            value = rollout.get(key, None)
            if value is None:
                raise MissingRolloutKeyError(
                    f"{name} needs the per-step cost {key!r}, which is missing "
                    f"from the rollout: put a cost with out_key={key!r} before it in the "
                    "CostSequence (TensorDictSequential)."
                )
            value = value.to(torch.float32)
            if isinstance(weight, float):
                value = weight * value
            else:
                factor = get_rollout_key(rollout, weight, name).to(torch.float32)
                if factor.numel() != value.numel():
                    raise ValueError(
                        f"the weight {weight!r} must hold one number per row of the acting "
                        f"tensordict ([*B, 1]), got shape {list(factor.shape)} in a rollout "
                        f"of {list(rollout.batch_size)}."
                    )
                value = factor.reshape(value.shape) * value
            total = value if total is None else total + value
        return total

    def extra_repr(self) -> str:
        return f"weights={self.weights!r}, {super().extra_repr()}"


class FirstArrival(RolloutCost):
    """Ends each candidate at the first step a target term calls reached: later steps cost ``inf``.

    A policy that stops following a plan once its target is reached (DORP's waypoints)
    executes only the plan's steps up to that first arrival, so that is where a plan
    should be judged: folded with ``"min"``, a candidate's score is then its cost at the
    first arrival (or its best step if it never arrives), not at a later step that
    would never run. Steps up to and including the first arrival keep ``cost_key``'s
    values.

    Args:
        reached_key: the per-step term ``[*B, N, H]`` that says whether the target is
            reached (e.g. a :class:`CodeMatchCost`'s out key: below ``threshold``).
        cost_key: the per-step cost ``[*B, N, H]`` to cut.
        threshold: a step is an arrival when ``reached_key`` is below it.
        out_key: where the cut cost is written (default: over ``cost_key``).
        step_aggregation: how planners fold the steps (default ``"min"``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import FirstArrival
        >>> rollout = TensorDict(
        ...     {"code_cost": torch.tensor([[1.0, 0.0, 0.0, 1.0]]),
        ...      "cost": torch.tensor([[1.2, 0.1, 0.05, 1.0]])},
        ...     batch_size=(1, 4),
        ... )
        >>> FirstArrival("code_cost")(rollout)["cost"]
        tensor([[1.2000, 0.1000,    inf,    inf]])
    """

    def __init__(
        self,
        reached_key: NestedKey,
        *,
        cost_key: NestedKey = "cost",
        threshold: float = 0.5,
        out_key: NestedKey | None = None,
        step_aggregation: str = "min",
    ) -> None:
        cost_key = unravel_key(cost_key)
        super().__init__(
            out_key=cost_key if out_key is None else out_key, step_aggregation=step_aggregation
        )
        self.reached_key = unravel_key(reached_key)
        self.cost_key = cost_key
        self.threshold = check_float("threshold", threshold)
        self.in_keys = list(dict.fromkeys([self.cost_key, self.reached_key]))

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        name = type(self).__name__
        cost = get_rollout_key(rollout, self.cost_key, name).to(torch.float32)
        reached = get_rollout_key(rollout, self.reached_key, name).reshape(cost.shape)
        hit = (reached < self.threshold).to(torch.int64)
        after = (hit.cumsum(-1) - hit) > 0  # an arrival at an earlier step
        return cost.masked_fill(after, math.inf)

    def extra_repr(self) -> str:
        return (
            f"reached_key={self.reached_key!r}, threshold={self.threshold}, {super().extra_repr()}"
        )


class NegativeRewardCost(RolloutCost):
    """Minus the planning env's reward at each step (for reward-defining model envs).

    Rewards after the first ``done`` of a candidate do not count (cost 0), as in
    torchrl's own ``CEMPlanner`` and ``MPPIPlanner``: the imagined rollout runs for the
    whole horizon, but an episode that ended earns nothing more. The reward of the step
    that sets ``done`` counts.

    Args:
        reward_key: the reward in the rollout, ``[*B, N, H]`` or ``[*B, N, H, 1]``.
        done_key: the done flag in the rollout (same shapes); ``None``: the planning env
            never ends an episode and every reward counts.
        out_key: where the per-step cost ``[*B, N, H]`` is written.
        step_aggregation: how planners fold the steps (default ``"sum"``: the return).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from dorp_rl.planners import NegativeRewardCost
        >>> done = torch.tensor([False, True, False, False]).expand(2, 5, 4).unsqueeze(-1)
        >>> rollout = TensorDict(
        ...     {("next", "reward"): torch.ones(2, 5, 4, 1), ("next", "done"): done},
        ...     batch_size=(2, 5, 4),
        ... )
        >>> NegativeRewardCost()(rollout)["cost"][0, 0]
        tensor([-1., -1.,  0.,  0.])
    """

    def __init__(
        self,
        reward_key: NestedKey = ("next", "reward"),
        *,
        done_key: NestedKey | None = ("next", "done"),
        out_key: NestedKey = "cost",
        step_aggregation: str = "sum",
    ) -> None:
        super().__init__(out_key=out_key, step_aggregation=step_aggregation)
        self.reward_key = unravel_key(reward_key)
        self.done_key = None if done_key is None else unravel_key(done_key)
        self.in_keys = [self.reward_key] + ([] if self.done_key is None else [self.done_key])

    def per_step_cost(self, rollout: TensorDictBase) -> torch.Tensor:
        name = type(self).__name__
        reward = get_rollout_key(rollout, self.reward_key, name)
        cost = -reward.reshape(rollout.batch_size).to(torch.float32)
        if self.done_key is not None:
            done = get_rollout_key(rollout, self.done_key, name)
            done = done.reshape(rollout.batch_size).to(torch.int64)
            # Steps after the first done along the horizon (the last batch dimension).
            ended = done.cumsum(-1) > done
            cost = cost.masked_fill(ended, 0.0)
        return cost

    def extra_repr(self) -> str:
        return f"reward_key={self.reward_key!r}, done_key={self.done_key!r}, {super().extra_repr()}"
