"""Evaluation: ground-truth diagnostics of learned codes, open-loop accuracy of world models."""

from dorp_rl.eval.diagnostics import (
    best_assignment,
    connected_fraction,
    encode_pixels,
    key_room_code_maps,
    key_room_diagnostics,
    rearrangement_code_maps,
    rearrangement_diagnostics,
    sample_rearrangement_states,
)
from dorp_rl.eval.world_model import open_loop_accuracy

__all__ = [
    "best_assignment",
    "connected_fraction",
    "encode_pixels",
    "key_room_code_maps",
    "key_room_diagnostics",
    "open_loop_accuracy",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "sample_rearrangement_states",
]
