"""Losses (torchrl LossModules): CPCLoss."""

from dorp_rl.objectives.cpc import CPCLoss, standardize_codes

__all__ = ["CPCLoss", "standardize_codes"]
