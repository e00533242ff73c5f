"""Pictures: upscaled frames, PNG strips (code maps and histograms come with the encoder)."""

from dorp_rl.viz.frames import frame_grid, frames_to_rgb_array, save_frame_strip, upscale_frames

__all__ = ["frame_grid", "frames_to_rgb_array", "save_frame_strip", "upscale_frames"]
