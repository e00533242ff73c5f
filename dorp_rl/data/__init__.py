"""Play data: collection into TorchRL replay buffers, pair and sequence samplers."""

from dorp_rl.data.play import (
    PLAY_KEYS,
    UniformRandomPolicy,
    collect_play_data,
    load_play_data,
    play_env,
)
from dorp_rl.data.samplers import FuturePairSampler, SequenceSampler, future_pairs

__all__ = [
    "FuturePairSampler",
    "SequenceSampler",
    "future_pairs",
    "PLAY_KEYS",
    "UniformRandomPolicy",
    "collect_play_data",
    "load_play_data",
    "play_env",
]
