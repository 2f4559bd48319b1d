"""torchmocap.filters."""
