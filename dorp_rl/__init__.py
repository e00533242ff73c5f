"""dorp-rl: DORP (Discrete Object-factorized Representation Planning) on TorchRL."""

__version__ = "0.1.0"
