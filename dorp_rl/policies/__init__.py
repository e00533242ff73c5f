"""Policies: the paper's visual-foresight baselines (and, later, DORP's hierarchical policy)."""

from dorp_rl.policies.visual_foresight import VARIANT_DEFAULTS, VisualForesightPolicy

__all__ = ["VARIANT_DEFAULTS", "VisualForesightPolicy"]
