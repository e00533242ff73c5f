"""Measures of codes and models, used by the trainers while they train and by the evaluation.

- :mod:`~dorp_rl.metrics.code_information`: label-free statistics of codes (information
  per one-hot; how codes change, are undone and die along play);
- :mod:`~dorp_rl.metrics.diagnostics`: ground-truth code diagnostics (selectivity,
  purity, temporal consistency) from labelled transitions (a profile's ``objects``), the
  measures an env's own diagnostics are built from;
- :mod:`~dorp_rl.metrics.world_model`: open-loop accuracy of a video prediction model.

Nothing here imports the trainers, the policies or the evaluation harness, so each of
them can use these. :mod:`dorp_rl.eval` re-exports every public name.
"""

from dorp_rl.metrics.code_information import code_dynamics, code_information, play_code_dynamics
from dorp_rl.metrics.diagnostics import (
    best_assignment,
    connected_fraction,
    encode_pixels,
    encode_states,
    fraction_true,
    majority_codes,
    mean_steps_random_pair,
    mean_steps_within_code,
    object_diagnostics,
    play_object_diagnostics,
)
from dorp_rl.metrics.world_model import latent_open_loop_accuracy, open_loop_accuracy

__all__ = [
    "best_assignment",
    "code_dynamics",
    "code_information",
    "connected_fraction",
    "encode_pixels",
    "encode_states",
    "fraction_true",
    "majority_codes",
    "mean_steps_random_pair",
    "mean_steps_within_code",
    "object_diagnostics",
    "latent_open_loop_accuracy",
    "open_loop_accuracy",
    "play_code_dynamics",
    "play_object_diagnostics",
]
