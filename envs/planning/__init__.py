"""Planning envs: models of the pixel environments that a planner can step in bulk.

A model-predictive planner imagines ``N`` candidate action sequences for each of ``B``
acting envs, so it needs an environment it can step on a ``[B, N]`` batch of copies of
the current situation. The two envs here are such models. Both are stateless TorchRL
:class:`~torchrl.envs.EnvBase` subclasses with ``batch_size=()`` and
``batch_locked=False`` (any leading shape), and both produce ``pixels``, so one cost
(for example :class:`~dorp_rl.planners.PixelDistanceCost`) works on either:

- :class:`GroundTruthModelEnv` steps copies of the true configuration ``state`` with the
  environment's own dynamics and renders them: the "ground-truth model" of the paper.
- :class:`VideoModelEnv` predicts the next frame from the current frame and the action
  with a learned video prediction model.

Keys (leading shape ``*B`` arbitrary):

- ``pixels``: uint8 ``[*B, 3, 16, 16]``, the (predicted) frame;
- ``goal_pixels``: uint8 ``[*B, 3, 16, 16]``, copied unchanged from input to output
  when present, so that a goal rides along with the rollout;
- ``state``: int64 configuration (:class:`GroundTruthModelEnv` only);
- ``action``: int64 ``[*B, 1]`` under a :class:`~torchrl.data.Categorical` spec;
- ``reward`` (always 0: planners score rollouts with separate cost modules) and
  ``done`` / ``terminated`` / ``truncated`` (always ``False``: imagined rollouts run for
  the whole horizon).

Imagining candidates without stepping
    A planner steps any planning env one horizon step at a time. An env that can do
    better declares ``imagine_candidates(td, actions, next_keys)`` on its class: from
    the acting rows ``td [b]`` and the actions ``[b, N, H]`` of every candidate at every
    step, it returns ``(rollout, lazy)``: ``rollout [b, N, H]`` holding ``action`` and
    the requested ``("next", key)`` values it computes, and ``lazy``, a dict from the
    other requested keys to :class:`LazyValue` objects computed only on demand (a cost
    that knows them reads them for less, the others get them materialised); or
    ``None`` when it cannot give these keys (``next_keys=None`` asks for all of them),
    and the planner steps it. The values must be those that stepping would give.
    :meth:`GroundTruthModelEnv.imagine_candidates` is one: states from
    :meth:`~GroundTruthModelEnv.imagine`, frames as lazy :class:`ImaginedFrames`.
"""

from dorp_rl.envs.planning.base import (
    FramePredictor,
    LazyValue,
    PlanningEnvBase,
    PlanningEnvSpecs,
    check_planning_action,
)
from dorp_rl.envs.planning.frame_hash import distinct_rows, int64_columns, row_hashes
from dorp_rl.envs.planning.imagined_frames import HeldFrames, ImaginedFrames, RolloutFrames
from dorp_rl.envs.planning.stateless import StatelessEnvModel
from dorp_rl.envs.planning.true_dynamics import GroundTruthModelEnv
from dorp_rl.envs.planning.video_model import (
    DEFAULT_PREDICT_CHUNK,
    FramePredictorModel,
    VideoModelEnv,
)

__all__ = [
    "DEFAULT_PREDICT_CHUNK",
    "FramePredictor",
    "FramePredictorModel",
    "GroundTruthModelEnv",
    "HeldFrames",
    "ImaginedFrames",
    "LazyValue",
    "PlanningEnvBase",
    "PlanningEnvSpecs",
    "RolloutFrames",
    "StatelessEnvModel",
    "VideoModelEnv",
    "check_planning_action",
    "distinct_rows",
    "int64_columns",
    "row_hashes",
]
