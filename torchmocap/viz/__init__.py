"""torchmocap.viz."""
