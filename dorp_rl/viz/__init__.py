"""Pictures: upscaled frames and PNG strips, code maps, factorization histograms, results."""

from dorp_rl.viz.code_maps import (
    code_colours,
    plot_factorization_histogram,
    plot_key_room_code_map,
    plot_rearrangement_code_map,
    write_diagnostic_plots,
)
from dorp_rl.viz.frames import frame_grid, frames_to_rgb_array, save_frame_strip, upscale_frames
from dorp_rl.viz.results import plot_results, plot_steps_vs_bound, plot_success

__all__ = [
    "code_colours",
    "frame_grid",
    "frames_to_rgb_array",
    "plot_factorization_histogram",
    "plot_key_room_code_map",
    "plot_rearrangement_code_map",
    "plot_results",
    "plot_steps_vs_bound",
    "plot_success",
    "save_frame_strip",
    "upscale_frames",
    "write_diagnostic_plots",
]
