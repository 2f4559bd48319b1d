"""torchmocap.body."""
