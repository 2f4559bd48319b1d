"""torchmocap.ik."""
