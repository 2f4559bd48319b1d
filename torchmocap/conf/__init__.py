"""Hydra configs shipped with the package (primary configs and config groups)."""
