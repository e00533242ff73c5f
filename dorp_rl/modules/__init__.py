"""Models as TensorDict-friendly modules: code encoder, similarity matrices, video prediction
model, latent world model."""

from dorp_rl.modules.encoder import (
    DiscreteCodeEncoder,
    EncoderConfig,
    check_pixels,
    choose_map_stride,
)
from dorp_rl.modules.latent import LatentModelConfig, LatentWorldModel
from dorp_rl.modules.similarity import (
    SIMILARITIES,
    DDDPSimilarity,
    FullSimilarity,
    IdentitySimilarity,
    make_similarity,
)
from dorp_rl.modules.video import (
    VideoModelConfig,
    VideoPredictionModel,
    palette_from_frames,
)

__all__ = [
    "DDDPSimilarity",
    "DiscreteCodeEncoder",
    "EncoderConfig",
    "FullSimilarity",
    "IdentitySimilarity",
    "LatentModelConfig",
    "LatentWorldModel",
    "SIMILARITIES",
    "VideoModelConfig",
    "VideoPredictionModel",
    "check_pixels",
    "choose_map_stride",
    "make_similarity",
    "palette_from_frames",
]
