"""Losses (torchrl LossModules): CPCLoss, VideoPredictionLoss, LatentWorldModelLoss."""

from dorp_rl.objectives.cpc import CPCLoss, standardize_codes
from dorp_rl.objectives.latent import LatentWorldModelLoss
from dorp_rl.objectives.video import VideoPredictionLoss

__all__ = ["CPCLoss", "LatentWorldModelLoss", "VideoPredictionLoss", "standardize_codes"]
