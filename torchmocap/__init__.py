"""torchmocap: particle-based articulated human motion capture in PyTorch."""

__version__ = "0.1.0"
