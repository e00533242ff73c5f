"""Play data: collection into TorchRL replay buffers, pair and sequence samplers."""

from dorp_rl.data.frame_scan import FrameScan, scan_frames
from dorp_rl.data.play import (
    MATCH_FIELDS,
    PLAY_KEYS,
    RESET_PROBES,
    UniformRandomPolicy,
    check_play_buffer,
    check_sampler_fits,
    choose_play_length,
    collect_play_data,
    load_play_data,
    play_env,
    play_keys,
    play_segment_length,
)
from dorp_rl.data.samplers import (
    EventWindowSampler,
    FuturePairSampler,
    SequenceSampler,
    changed_pixels,
    event_transitions,
    future_pairs,
    rare_code_changes,
)

__all__ = [
    "FrameScan",
    "scan_frames",
    "EventWindowSampler",
    "FuturePairSampler",
    "SequenceSampler",
    "changed_pixels",
    "event_transitions",
    "future_pairs",
    "rare_code_changes",
    "MATCH_FIELDS",
    "PLAY_KEYS",
    "RESET_PROBES",
    "UniformRandomPolicy",
    "check_play_buffer",
    "check_sampler_fits",
    "choose_play_length",
    "collect_play_data",
    "load_play_data",
    "play_env",
    "play_keys",
    "play_segment_length",
]
