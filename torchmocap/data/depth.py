"""Depth point clouds of a sequence: :class:`DepthData` (a modality of a
:class:`~torchmocap.data.Sequence`). One depth camera of Hauberg & Pedersen's stereo rig is
synthesised by :func:`torchmocap.data.synthetic.depth.synthesize_depth`.

Frames have different point counts: they are stored padded ``(T, N, 3)`` with ``counts (T,)``.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["DepthData"]

@dataclass
class DepthData:
    """Depth point clouds.

    Attributes:
        points: ``(T, N, 3)`` world points (m), zero-padded beyond ``counts``.
        counts: ``(T,)`` long, valid points per frame.
        camera: the depth camera (a one-camera :class:`~torchmocap.cameras.CameraRig`).
    """

    points: Tensor
    counts: Tensor
    camera: object

    def frame_points(self, t: int) -> Tensor:
        """``(counts[t], 3)`` points of frame ``t``."""
        return self.points[t, : int(self.counts[t])]
