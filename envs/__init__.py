"""The paper's pixel environments as batched, stateless TorchRL envs, and env profiles.

Each env declares its profile (:class:`EnvProfile`: name, factory, presets, DORP
settings, task drawing) next to it; :func:`env_profile` finds a profile by name or by an
import path, so a user's env goes through the same pipeline.

Importing this package also registers the gymnasium ids ``dorp_rl/ObjectRearrangement-v0``
(kwarg ``num_objects``), ``dorp_rl/KeyWall-v0`` and ``dorp_rl/KeyCorridor-v0``.
"""

from dorp_rl.envs.factory import ENV_NAMES, env_class, make_env
from dorp_rl.envs.grid_base import DIRECTIONS, GRID_SIZE, GridWorldEnv, paint_layers
from dorp_rl.envs.gymnasium_envs import GymnasiumGridEnv, register_gymnasium_envs
from dorp_rl.envs.gymnasium_goals import GymGoalEnv, draw_reachable_tasks
from dorp_rl.envs.key_room_diagnostics import (
    key_event_states,
    key_room_code_maps,
    key_room_diagnostics,
    plot_key_room_code_map,
)
from dorp_rl.envs.key_rooms import KeyCorridorEnv, KeyRoomEnv, KeyWallEnv
from dorp_rl.envs.latent_planning import LatentModelEnv, planning_dtype
from dorp_rl.envs.oracle import OracleCodeEncoder
from dorp_rl.envs.paper import DEFAULT_ENV
from dorp_rl.envs.planning import GroundTruthModelEnv, VideoModelEnv
from dorp_rl.envs.profile import (
    CodeDiagnostics,
    EnvProfile,
    env_profile,
    profile_of,
    register_env_profile,
    registered_profiles,
    reset_tasks,
)
from dorp_rl.envs.rearrangement import DEFAULT_MAX_STEPS, OBJECT_COLOURS, ObjectRearrangementEnv
from dorp_rl.envs.rearrangement_diagnostics import (
    rearrangement_code_maps,
    rearrangement_diagnostics,
    sample_rearrangement_states,
)
from dorp_rl.envs.spec import DiscreteActions, env_device, env_identity

register_gymnasium_envs()

__all__ = [
    "DEFAULT_ENV",
    "CodeDiagnostics",
    "OracleCodeEncoder",
    "key_event_states",
    "key_room_code_maps",
    "key_room_diagnostics",
    "plot_key_room_code_map",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "sample_rearrangement_states",
    "DEFAULT_MAX_STEPS",
    "DIRECTIONS",
    "DiscreteActions",
    "ENV_NAMES",
    "EnvProfile",
    "env_profile",
    "profile_of",
    "register_env_profile",
    "registered_profiles",
    "reset_tasks",
    "env_class",
    "env_device",
    "env_identity",
    "GRID_SIZE",
    "GridWorldEnv",
    "GroundTruthModelEnv",
    "GymGoalEnv",
    "GymnasiumGridEnv",
    "draw_reachable_tasks",
    "KeyCorridorEnv",
    "KeyRoomEnv",
    "KeyWallEnv",
    "make_env",
    "OBJECT_COLOURS",
    "ObjectRearrangementEnv",
    "paint_layers",
    "register_gymnasium_envs",
    "VideoModelEnv",
    "LatentModelEnv",
    "planning_dtype",
]
