"""torchmocap.io."""
