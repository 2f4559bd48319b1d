"""torchmocap.distributions."""
