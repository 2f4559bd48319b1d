"""torchmocap.likelihoods."""
