"""Models as TensorDict-friendly modules: the discrete code encoder and similarity matrices."""

from dorp_rl.modules.encoder import DiscreteCodeEncoder, EncoderConfig, check_pixels
from dorp_rl.modules.similarity import (
    SIMILARITIES,
    DDDPSimilarity,
    FullSimilarity,
    IdentitySimilarity,
    make_similarity,
)

__all__ = [
    "DDDPSimilarity",
    "DiscreteCodeEncoder",
    "EncoderConfig",
    "FullSimilarity",
    "IdentitySimilarity",
    "SIMILARITIES",
    "check_pixels",
    "make_similarity",
]
