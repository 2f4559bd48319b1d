"""torchmocap.skeleton."""
