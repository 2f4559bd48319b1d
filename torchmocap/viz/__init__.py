"""Figures: 3D skeleton sequences and projected skeleton/capsule overlays (matplotlib, Agg)."""

from torchmocap.viz.plots import (
    capsule_outlines,
    overlay_on_image,
    plot_skeleton_sequence,
    side_colors,
)

__all__ = ["capsule_outlines", "overlay_on_image", "plot_skeleton_sequence", "side_colors"]
