"""torchmocap.metrics."""
