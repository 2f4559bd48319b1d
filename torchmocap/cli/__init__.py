"""torchmocap.cli."""
