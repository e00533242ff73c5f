"""Pictures: upscaled frames and PNG strips, code maps, factorization histograms, results,
rollout GIFs with DORP's waypoint."""

from dorp_rl.viz.code_maps import (
    code_colours,
    plot_code_maps,
    plot_factorization_histogram,
    write_diagnostic_plots,
)
from dorp_rl.viz.frames import frame_grid, frames_to_rgb_array, save_frame_strip, upscale_frames
from dorp_rl.viz.results import plot_results, plot_steps_vs_bound, plot_success
from dorp_rl.viz.rollouts import (
    code_maps_for_waypoints,
    rollout_gif_frames,
    save_rollout_gif,
    waypoint_panel,
)

__all__ = [
    "code_colours",
    "code_maps_for_waypoints",
    "frame_grid",
    "frames_to_rgb_array",
    "plot_code_maps",
    "plot_factorization_histogram",
    "plot_results",
    "plot_steps_vs_bound",
    "plot_success",
    "rollout_gif_frames",
    "save_frame_strip",
    "save_rollout_gif",
    "upscale_frames",
    "waypoint_panel",
    "write_diagnostic_plots",
]
