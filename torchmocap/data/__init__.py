"""torchmocap.data."""
