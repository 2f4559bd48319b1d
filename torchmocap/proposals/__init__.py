"""torchmocap.proposals."""
