"""The real PARSEC bodytrack frame as a one-frame :class:`~torchmocap.data.Sequence`.

A bodytrack frame folder holds ``CALIB/Camera<i>.cal`` (Bouguet calibrations in millimetres),
``CAM<i>/image0000.bmp`` (640x480 grey images) and ``FG<i>/image0000.bmp`` (foreground masks);
lossless PNG copies (``image0000.png``, as in ``tests/data_files``) are read as well.
The loader carves the masks' visual hull, scales a human31 to the hull's height (the subject's
tracking skeleton, ``meta.subject_skeleton``) and places standing candidate poses at the hull's
centre, one per heading (``meta.initial_poses``) — what a tracker with
``refine_first_frame`` starts from (``tracker=real_frame``). No ground truth.

Masks are read by :func:`~torchmocap.io.frames.read_mask` (binary 0/N masks of any foreground
value N). Implausible inputs are reported: a view whose mask is more than half foreground (a
whole person covers 4-8 % of bodytrack's views: inverted or all-foreground masks) and a hull
whose height puts the subject outside the skeleton's scale range (the scale is then held at the
bound: masks or calibrations wrong, e.g. swapped) each give a warning; an empty hull is an error
that names each view's foreground.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchmocap.data.sources import data_source
from torchmocap.data.subjects.recorded import SCALE_RANGE

__all__ = ["SCALE_RANGE", "load_bodytrack", "load_bodytrack_sequence"]


def _frame_file(folder: Path) -> Path | None:
    """``image0000.bmp`` (PARSEC's files) or ``image0000.png`` (a lossless copy) in ``folder``."""
    for suffix in (".bmp", ".png"):
        p = folder / f"image0000{suffix}"
        if p.is_file():
            return p
    return None


def load_bodytrack(root: str | Path, scale: float = 1.0):
    """``(rig, images (C, H, W) uint8, masks (C, H, W) bool)`` of a bodytrack frame folder.

    Raises:
        FileNotFoundError: a missing folder, calibration, image or mask (named).
        CameraError: a gap in the calibration files' numbers (e.g. no ``Camera2.cal``).
        ValueError: unreadable images or masks of another size than the camera's.
    """
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from torchmocap.cameras import bouguet_calibration_files, read_bouguet_rig
    from torchmocap.inputs import note_input
    from torchmocap.io.frames import read_mask

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"data.path: no such folder: {root}")
    note_input(root)  # its CAM<i>/FG<i> folders decide the cameras
    if not any((root / "CALIB").glob("*.cal")):
        raise FileNotFoundError(f"data.path: no CALIB/Camera*.cal under {root}")
    if not (isinstance(scale, (int, float)) and 0 < scale <= 4):
        raise ValueError(f"data.scale: expected an image scale in (0, 4], got {scale!r}")
    # paired by the number in the name: Camera<i>.cal <-> CAM<i>/FG<i> (a gap is an error)
    cals = bouguet_calibration_files(root / "CALIB")
    rig = read_bouguet_rig([p for _, p in cals], unit="mm")
    have = {i for i, _ in cals}
    for d in sorted(root.glob("CAM*")):
        if d.is_dir() and d.name[3:].isdigit() and int(d.name[3:]) not in have:
            raise FileNotFoundError(f"data.path: {d.name} has no calibration "
                                    f"(CALIB/Camera{int(d.name[3:])}.cal missing in {root})")
    imgs, masks = [], []
    for c, (i, _) in enumerate(cals):
        img, fg = _frame_file(root / f"CAM{i}"), _frame_file(root / f"FG{i}")
        if img is None or fg is None:
            raise FileNotFoundError(f"data.path: camera {i} image or mask (CAM{i}/FG{i}/"
                                    f"image0000.bmp or .png) missing in {root}")
        for f in (img, fg):
            note_input(f.parent)  # image0000.bmp or .png: what is there decides
        note_input(img)
        try:
            a = Image.open(img).convert("L")
        except (UnidentifiedImageError, OSError) as e:
            raise ValueError(f"data.path: cannot read camera {i}'s image: {e}") from None
        want = tuple(int(v) for v in rig.image_size[c].tolist())
        if a.size != want:
            raise ValueError(f"data.path: camera {i}: image {a.size} differs from the "
                             f"calibrated image size {want}")
        m = Image.fromarray(read_mask(fg, want))
        if scale != 1.0:
            size = (round(a.width * scale), round(a.height * scale))
            a = a.resize(size, Image.BILINEAR)
            m = m.resize(size, Image.NEAREST)
        imgs.append(torch.from_numpy(np.asarray(a).copy()))
        masks.append(torch.from_numpy(np.asarray(m).copy()))
    if scale != 1.0:
        rig = rig.scaled_images(scale)
    return rig, torch.stack(imgs), torch.stack(masks)


def _numbers(rig) -> list[str]:
    """The camera numbers of a bodytrack rig (``Camera3`` -> ``3``)."""
    return [n.removeprefix("Camera") for n in rig.names]


@data_source(provides=("images", "silhouettes", "rig"), trackers=("real_frame", "real_frame_hull"))
def load_bodytrack_sequence(path: str | Path, scale: float = 1.0, headings: int = 12,
                            voxel: float = 0.04, checks: str = "refuse", seed: int = 0):
    """One bodytrack frame as a :class:`~torchmocap.data.Sequence` (``scenario="recorded"``).

    Args:
        path: the frame folder.
        scale: image scale (0.5 = 320x240).
        headings: number of candidate headings of the standing start poses.
        voxel: visual-hull voxel size (metres).
        checks: ``refuse`` or ``warn``: what masks that disagree with the other views' are
            (:func:`~torchmocap.data.recordings.checks.mask_consistency`; the report is
            ``meta.view_consistency``).
        seed: unused (the loader is deterministic); accepted like every data source's.
    """
    from torchmocap.data.metadata import SequenceMeta
    from torchmocap.data.recordings.checks import check_mode, check_views, mask_consistency
    from torchmocap.data.sequence import Sequence
    from torchmocap.data.subjects.recorded import hull_start

    check_mode(checks)
    root = Path(str(path)).expanduser().absolute()
    rig, images, masks = load_bodytrack(root, float(scale))
    labels = [f"FG{n}" for n in _numbers(rig)]
    consistency = mask_consistency(masks, rig, labels)  # the views' masks agree
    check_views(consistency, checks)
    start = hull_start(rig, masks, headings, float(voxel),
                       labels=[f"FG{n}" for n in _numbers(rig)])
    colour = images[..., None].expand(*images.shape, 3).contiguous()
    return Sequence(
        fps=25.0, scenario="recorded", rig=rig.float(), silhouettes=masks[None],
        view_dropped=torch.zeros(1, rig.num_cameras, dtype=torch.bool), images=colour[None],
        meta=SequenceMeta(source="bodytrack", path=str(root), suggested_tracker="real_frame",
                          view_consistency=consistency).update(start))
