"""Checks of the mask computation's inputs, and their resampling to the working resolution.

Views of different sizes share one array: ``images (T, C, H, W, 3)`` has the largest view's
size and a smaller view (``rig.image_size[c]``) occupies its top-left corner, the rest being
padding that is never foreground.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmocap.cameras.rig import CameraRig
from torchmocap.data.recordings.masks.settings import MaskError

__all__ = ["MAX_CODEC_CROP", "check_images", "check_keypoints", "check_plates", "resize_views"]

#: a plate may exceed its camera's decoded frame by fewer pixels than this per axis (encoders
#: code whole 16-pixel macroblocks and crop the rest on the right and bottom)
MAX_CODEC_CROP = 16


def check_images(images, rig) -> tuple[Tensor, Tensor]:
    """``images (T, C, H, W, 3)`` uint8 against ``rig``; returns them and the per-camera
    ``(C, 2)`` (width, height) sizes."""
    if not isinstance(rig, CameraRig):
        raise MaskError(f"rig: expected a CameraRig, got {type(rig).__name__}")
    C = rig.num_cameras
    if not isinstance(images, Tensor) or images.dim() != 5 or images.shape[1] != C or \
            images.shape[-1] != 3 or images.shape[0] < 1:
        got = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
        raise MaskError(f"images: expected a tensor of shape (T, {C}, H, W, 3) (RGB, one view "
                        f"per camera of the rig), got {got}")
    if images.dtype != torch.uint8:
        raise MaskError(f"images: expected uint8 RGB, got {images.dtype}")
    H, W = images.shape[2:4]
    sizes = rig.image_size.cpu()
    big = (sizes[:, 0] > W) | (sizes[:, 1] > H)
    if bool(big.any()) or int(sizes[:, 0].max()) != W or int(sizes[:, 1].max()) != H:
        raise MaskError(f"images: arrays of {W}x{H} (width x height) do not hold the rig's "
                        f"image sizes {sizes.tolist()}: expected the largest view's size (a "
                        "smaller view fills the top-left corner)")
    return images, sizes


def check_plates(plates, sizes: Tensor) -> list[Tensor | None] | None:
    """Background plates (``None``, a ``(C, H', W', 3)`` uint8 tensor, or ``C`` tensors
    ``(H'_c, W'_c, 3)`` or None) against the cameras' ``sizes (C, 2)``: each at least as large
    as its camera's frames and larger by a codec crop only."""
    if plates is None:
        return None
    C = sizes.shape[0]
    if isinstance(plates, Tensor):
        if plates.dim() != 4 or plates.shape[0] != C or plates.shape[-1] != 3:
            raise MaskError(f"backgrounds: expected shape ({C}, H, W, 3) (one RGB plate per "
                            f"camera), got {tuple(plates.shape)}")
        plates = list(plates)
    elif not isinstance(plates, Sequence) or isinstance(plates, (str, bytes)) or \
            len(plates) != C:
        n = len(plates) if isinstance(plates, Sequence) else type(plates).__name__
        raise MaskError(f"backgrounds: expected {C} plates (one per camera, None for none), "
                        f"got {n}")
    out: list[Tensor | None] = []
    for c, p in enumerate(plates):
        if p is None:
            out.append(None)
            continue
        if not isinstance(p, Tensor) or p.dim() != 3 or p.shape[-1] != 3 or p.numel() == 0:
            got = tuple(p.shape) if isinstance(p, Tensor) else type(p).__name__
            raise MaskError(f"backgrounds[{c}]: expected a non-empty (H, W, 3) RGB plate, got "
                            f"{got}")
        if p.dtype != torch.uint8:
            raise MaskError(f"backgrounds[{c}]: expected uint8 RGB, got {p.dtype}")
        w, h = (int(v) for v in sizes[c])
        dh, dw = p.shape[0] - h, p.shape[1] - w
        if not (0 <= dh < MAX_CODEC_CROP and 0 <= dw < MAX_CODEC_CROP):
            raise MaskError(
                f"backgrounds[{c}]: a {p.shape[1]}x{p.shape[0]} plate does not fit camera {c}'s "
                f"{w}x{h} frames (width x height): expected the same size or larger by a codec "
                f"crop of under {MAX_CODEC_CROP} px on the right/bottom")
        if int(p.amax()) == int(p.amin()):
            raise MaskError(f"backgrounds[{c}]: the plate is blank (every pixel {int(p.amax())})")
        out.append(p)
    return out


def check_keypoints(keypoints, shape: tuple[int, int]) -> Tensor | None:
    """``keypoints (T, C, K, 3)`` (u, v, confidence): confidences finite and ≥ 0, pixels
    finite where the confidence is positive."""
    if keypoints is None:
        return None
    T, C = shape
    if not isinstance(keypoints, Tensor) or keypoints.dim() != 4 or \
            tuple(keypoints.shape[:2]) != (T, C) or keypoints.shape[-1] != 3:
        got = tuple(keypoints.shape) if isinstance(keypoints, Tensor) else \
            type(keypoints).__name__
        raise MaskError(f"keypoints: expected shape ({T}, {C}, K, 3) (u, v, confidence per "
                        f"frame, camera and keypoint), got {got}")
    kp = keypoints.to(torch.float64) if keypoints.is_floating_point() else keypoints.double()
    conf = kp[..., 2]
    if not bool(torch.isfinite(conf).all()) or bool((conf < 0).any()):
        raise MaskError("keypoints: expected finite confidences >= 0 (0 = not detected)")
    if not bool(torch.isfinite(kp[..., :2])[conf > 0].all()):
        raise MaskError("keypoints: expected finite pixel coordinates where the confidence is "
                        "positive")
    return kp


def resize_views(images: Tensor, sizes: Tensor, out_sizes: Tensor) -> Tensor:
    """Resample each view's region of ``images (T, C, H, W, 3)`` uint8 from ``sizes`` to
    ``out_sizes`` ((C, 2) width, height; antialiased bilinear) into a zero-padded
    ``(T, C, 3, h, w)`` uint8 array of the largest output size."""
    T, C = images.shape[:2]
    w_out, h_out = int(out_sizes[:, 0].max()), int(out_sizes[:, 1].max())
    out = torch.zeros(T, C, 3, h_out, w_out, dtype=torch.uint8, device=images.device)
    for c in range(C):
        w, h = (int(v) for v in sizes[c])
        wo, ho = (int(v) for v in out_sizes[c])
        x = images[:, c, :h, :w].permute(0, 3, 1, 2)  # channels-last memory, as decoded
        if (wo, ho) == (w, h):
            y = x
        elif x.device.type == "cpu":
            y = F.interpolate(x.contiguous(memory_format=torch.channels_last), size=(ho, wo),
                              mode="bilinear", antialias=True, align_corners=False)
        else:
            y = F.interpolate(x.float(), size=(ho, wo), mode="bilinear", antialias=True,
                              align_corners=False).round().clamp(0, 255).to(torch.uint8)
        out[:, c, :, :ho, :wo] = y
    return out
