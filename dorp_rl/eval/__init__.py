"""Evaluation: ground-truth diagnostics of learned codes (task sets and the harness come later)."""

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

__all__ = [
    "best_assignment",
    "connected_fraction",
    "encode_pixels",
    "key_room_code_maps",
    "key_room_diagnostics",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "sample_rearrangement_states",
]
