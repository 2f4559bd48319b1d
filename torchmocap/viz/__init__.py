"""Figures: 3D skeleton sequences and projected skeleton/capsule overlays (matplotlib, Agg);
multi-view overlay grids of a track (estimate and truth, legend) and their animations."""

from torchmocap.viz.overlays import (
    ESTIMATE_COLOR,
    TRUTH_COLOR,
    render_overlay_grid,
    track_overlay_frames,
    write_overlay_grid,
)
from torchmocap.viz.plots import (
    capsule_outlines,
    overlay_on_image,
    plot_skeleton_sequence,
    side_colors,
)
from torchmocap.viz.video import write_video

__all__ = [
    "ESTIMATE_COLOR",
    "TRUTH_COLOR",
    "capsule_outlines",
    "overlay_on_image",
    "plot_skeleton_sequence",
    "render_overlay_grid",
    "side_colors",
    "track_overlay_frames",
    "write_overlay_grid",
    "write_video",
]
