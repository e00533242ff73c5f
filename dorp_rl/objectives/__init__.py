"""Losses (torchrl LossModules): CPCLoss, VideoPredictionLoss."""

from dorp_rl.objectives.cpc import CPCLoss, standardize_codes
from dorp_rl.objectives.video import VideoPredictionLoss

__all__ = ["CPCLoss", "VideoPredictionLoss", "standardize_codes"]
