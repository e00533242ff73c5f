"""The paper's pixel environments as batched, stateless TorchRL envs.

Importing this package also registers the gymnasium ids ``dorp_rl/ObjectRearrangement-v0``
(kwarg ``num_objects``), ``dorp_rl/KeyWall-v0`` and ``dorp_rl/KeyCorridor-v0``.
"""

from dorp_rl.envs.factory import ENV_NAMES, env_class, make_env
from dorp_rl.envs.grid_base import DIRECTIONS, GRID_SIZE, GridWorldEnv, paint_layers
from dorp_rl.envs.gymnasium_envs import GymnasiumGridEnv, register_gymnasium_envs
from dorp_rl.envs.key_rooms import KeyCorridorEnv, KeyRoomEnv, KeyWallEnv
from dorp_rl.envs.planning import GroundTruthModelEnv, WorldModelEnv
from dorp_rl.envs.rearrangement import DEFAULT_MAX_STEPS, OBJECT_COLOURS, ObjectRearrangementEnv
from dorp_rl.envs.spec import DiscreteActions, env_device, env_identity

register_gymnasium_envs()

__all__ = [
    "DEFAULT_MAX_STEPS",
    "DIRECTIONS",
    "DiscreteActions",
    "ENV_NAMES",
    "env_class",
    "env_device",
    "env_identity",
    "GRID_SIZE",
    "GridWorldEnv",
    "GroundTruthModelEnv",
    "GymnasiumGridEnv",
    "KeyCorridorEnv",
    "KeyRoomEnv",
    "KeyWallEnv",
    "make_env",
    "OBJECT_COLOURS",
    "ObjectRearrangementEnv",
    "paint_layers",
    "register_gymnasium_envs",
    "WorldModelEnv",
]
