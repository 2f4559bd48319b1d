"""Foreground masks of real multi-view recordings that ship none.

:func:`compute_masks` is the entry point: a background model per camera (the video's temporal
median, corrected by a registered background plate where the two disagree), a shadow-robust
colour difference thresholded at each camera's noise, morphological cleanup, and a multi-view
check (the reprojected visual hull supported by C − 1 views, and the subject's keypoint box).
:func:`cached_masks` stores the result as 1-bit PNGs under a content hash of the inputs and
settings; :func:`write_mask_preview` draws what was kept and what the checks removed.

Example:
    >>> import torch
    >>> from torchmocap.cameras import make_ring_rig
    >>> frames = torch.randint(0, 255, (2, 4, 48, 64, 3), dtype=torch.uint8)
    >>> masks, report = compute_masks(frames, make_ring_rig(4, image_size=(64, 48)),
    ...                               settings={"scale": 0.5, "multiview": False})
    >>> masks.shape, masks.dtype
    (torch.Size([2, 4, 24, 32]), torch.bool)
"""

from torchmocap.data.recordings.masks.background import BackgroundModel, estimate_background
from torchmocap.data.recordings.masks.cache import (
    cached_masks,
    content_key,
    read_mask_folder,
    write_mask_folder,
)
from torchmocap.data.recordings.masks.consistency import hull_filter, hull_regions, keypoint_gate
from torchmocap.data.recordings.masks.foreground import (
    clean_masks,
    colour_distortion,
    foreground_masks,
)
from torchmocap.data.recordings.masks.pipeline import compute_masks, working_images, working_sizes
from torchmocap.data.recordings.masks.preview import mask_preview, write_mask_preview
from torchmocap.data.recordings.masks.registration import register_images, warp_images
from torchmocap.data.recordings.masks.settings import MaskError, MaskSettings

__all__ = [
    "BackgroundModel",
    "MaskError",
    "MaskSettings",
    "cached_masks",
    "clean_masks",
    "colour_distortion",
    "compute_masks",
    "content_key",
    "estimate_background",
    "foreground_masks",
    "hull_filter",
    "hull_regions",
    "keypoint_gate",
    "mask_preview",
    "read_mask_folder",
    "register_images",
    "warp_images",
    "working_images",
    "working_sizes",
    "write_mask_folder",
    "write_mask_preview",
]
