"""torchmocap.cameras."""
