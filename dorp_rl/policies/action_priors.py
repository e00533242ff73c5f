"""Action priors of the DORP policy: which actions its planners sample more often.

The play data's action counts (:meth:`~dorp_rl.planners.CodeGraph.action_weights`) say
which actions moved which one-hots. With ``action_prior_mix > 0`` the waypoint planner
draws its candidates from the actions that moved the hop's one-hots; with
``goal_action_prior_mix > 0`` the goal planner draws from those that moved the objects
still off their goal place. Each prior is mixed with uniform draws, so no action is left
out.

Examples:
    >>> import torch
    >>> from dorp_rl.policies.action_priors import mixed
    >>> mixed(torch.tensor([[1.0, 0.0]]), 0.5).tolist()  # half the draws from the prior
    [[0.75, 0.25]]
"""

from __future__ import annotations

import torch
from torch import nn

from dorp_rl.modules.encoder import eval_mode, module_device
from dorp_rl.planners.base import DiscreteMPCPlanner
from dorp_rl.planners.code_graph import CodeGraph

__all__ = ["check_action_prior", "goal_action_prior", "mixed", "waypoint_action_prior"]


def check_action_prior(
    name: str, mix: float, planner: DiscreteMPCPlanner, key: str, missing: str | None
) -> None:
    """Refuses a prior share ``mix > 0`` whose planner does not sample from ``key``, or
    (``missing``: what it lacks) whose parts cannot make the prior."""
    if mix <= 0:
        return
    if planner.action_prior_key != key:
        raise ValueError(
            f"{name}={mix} needs a planner that samples from {key!r} "
            f"(action_prior_key={key!r}), got action_prior_key={planner.action_prior_key!r}."
        )
    if missing is not None:
        raise ValueError(f"{name}={mix} needs {missing} pass {name}=0.")


def mixed(weights: torch.Tensor, mix: float) -> torch.Tensor:
    """``[rows, A]`` action shares ``weights`` mixed with uniform draws (``mix``: their share)."""
    return mix * weights + (1.0 - mix) / weights.shape[-1]


def waypoint_action_prior(
    graph: CodeGraph,
    code: torch.Tensor,
    subgoal_code: torch.Tensor,
    subgoal_mask: torch.Tensor,
    num_actions: int,
    mix: float,
) -> torch.Tensor:
    """``[rows, A]``: the action shares of the one-hots a hop changes (codes ``[rows, C]``,
    the waypoint's codes and mask ``[rows, C]``), mixed with uniform draws."""
    hop = (subgoal_code != code) & subgoal_mask
    return mixed(graph.action_weights(hop, num_actions), mix)


@torch.no_grad()
def goal_action_prior(
    encoder: nn.Module,
    graph: CodeGraph,
    pixels: torch.Tensor,
    goal_pixels: torch.Tensor,
    num_actions: int,
    mix: float,
) -> torch.Tensor:
    """``[rows, A]``: the action shares of the objects still off their goal place (object
    maps ``encoder.object_maps`` of ``pixels`` farther from those of ``goal_pixels`` than a
    quarter of the farthest), mixed with uniform draws."""
    with eval_mode(encoder):
        both = torch.cat([pixels, goal_pixels]).to(module_device(encoder))
        maps = encoder.object_maps(both).float()
    current, goal = maps.split(pixels.shape[0])
    distance = (current - goal).flatten(2).norm(dim=-1).cpu()  # [rows, K]
    farthest = distance.max(-1, keepdim=True).values
    off = (distance > 0.25 * farthest) & (farthest > 0)
    return mixed(graph.action_weights(off, num_actions), mix)
