"""Visual foresight (VF-RS, VF-CEM): the paper's baselines, planning on pixel distance.

The policy imagines candidate action sequences in a planning env (a video prediction
model through :class:`~dorp_rl.envs.VideoModelEnv`, or the true dynamics through
:class:`~dorp_rl.envs.GroundTruthModelEnv`) and picks the one whose predicted frames
come closest to the goal image ``goal_pixels`` in pixel L2
(:class:`~dorp_rl.planners.PixelDistanceCost`).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, TensorDictPrimer

from dorp_rl.planners.base import DiscreteMPCPlanner
from dorp_rl.planners.cem import CategoricalCEMPlanner
from dorp_rl.planners.costs import PixelDistanceCost
from dorp_rl.planners.random_shooting import RandomShootingPlanner
from dorp_rl.validation import check_keywords, keyword_names

#: Defaults of each variant (the paper: 1000 sequences of 14 steps; CEM top 2 % = 20
#: elites, 3 optimisation steps).
VARIANT_DEFAULTS: dict[str, dict[str, Any]] = {
    "rs": {"planning_horizon": 14, "num_candidates": 1000, "execution": "open_loop"},
    "cem": {
        "planning_horizon": 14,
        "num_candidates": 1000,
        "execution": "open_loop",
        "optim_steps": 3,
        "top_k": 20,
    },
}


class VisualForesightPolicy(TensorDictModuleBase):
    """VF-RS / VF-CEM: a discrete MPC planner minimising pixel L2 to ``goal_pixels``.

    - ``variant="rs"``: :class:`~dorp_rl.planners.RandomShootingPlanner`, 1000 random
      sequences of 14 steps, the best one executed open loop (as the paper).
    - ``variant="cem"``: :class:`~dorp_rl.planners.CategoricalCEMPlanner`, 1000 samples
      per optimisation step, ``top_k=20`` elites (top 2 %), ``optim_steps=3``, also
      executed open loop by default (pass ``execution="receding"`` to replan at every
      step, with warm start). ``top_k`` is a count: lower it with ``num_candidates``.

    ``step_aggregation`` says how the per-step pixel distances of a sequence fold into
    its score. ``"min"`` (default): a sequence is scored by the closest its predicted
    frames get to the goal and executed up to that frame, as the authors' release does
    for its goal step; ``"final"`` gives the literal "best full sequence" reading (score
    the last frame, execute all steps). Any other keyword goes to the planner
    (``planning_horizon``, ``num_candidates``, ``action_repeat``, ``seed``, ...).

    It is a policy for ``env.rollout(max_steps, policy)`` and for
    :class:`torchrl.collectors.Collector`. Its state (the plan being executed) lives in
    the tensordict under the planner's keys; a collector needs them declared on the env:
    pass ``auto_register_policy_transforms=True`` to the collector, or append
    :meth:`make_primer` to the env yourself.

    Args:
        planning_env: a planning env that produces ``pixels`` (not batch-locked).
        variant: ``"rs"`` or ``"cem"``.
        goal_key: the goal image in the acting env's tensordict.
        step_aggregation: ``"min"`` (default), ``"final"`` or ``"sum"``.
        **planner_kwargs: overrides of the planner's arguments.

    Examples:
        >>> from dorp_rl.envs import GroundTruthModelEnv, ObjectRearrangementEnv
        >>> from dorp_rl.policies import VisualForesightPolicy
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(2,), seed=0)
        >>> policy = VisualForesightPolicy(
        ...     GroundTruthModelEnv(env), "cem", planning_horizon=6, num_candidates=100, seed=0
        ... )
        >>> td = env.rollout(4, policy)
        >>> td["action"].shape
        torch.Size([2, 4, 1])
    """

    def __init__(
        self,
        planning_env: EnvBase,
        variant: str = "cem",
        *,
        goal_key: NestedKey = "goal_pixels",
        step_aggregation: str = "min",
        **planner_kwargs: Any,
    ) -> None:
        super().__init__()
        if variant not in VARIANT_DEFAULTS:
            raise ValueError(f"variant must be one of {sorted(VARIANT_DEFAULTS)}, got {variant!r}.")
        self.variant = variant
        planner_cls = RandomShootingPlanner if variant == "rs" else CategoricalCEMPlanner
        accepted = set(keyword_names(planner_cls)) - {"env", "cost"}
        check_keywords(planner_kwargs, accepted, f"VisualForesightPolicy({variant!r})")
        kwargs = {**VARIANT_DEFAULTS[variant], **planner_kwargs}
        cost = PixelDistanceCost(goal_key=goal_key, step_aggregation=step_aggregation)
        self.planner: DiscreteMPCPlanner = planner_cls(planning_env, cost, **kwargs)
        self.in_keys = list(self.planner.in_keys)
        self.out_keys = list(self.planner.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.planner(tensordict)

    def make_primer(self) -> TensorDictPrimer:
        """The planner's :class:`~torchrl.envs.TensorDictPrimer` (see the class docstring)."""
        return self.planner.make_primer()

    def set_seed(self, seed: int | None) -> None:
        """Reseeds the planner's generator."""
        self.planner.set_seed(seed)

    @property
    def generator(self) -> torch.Generator:
        return self.planner.generator
