"""Self-occlusion of joints by the body surface, per camera (for simulated 2D detections).

A joint ``j`` at camera depth ``z_j`` is *occluded* in a view when the nearest surface at its
pixel (the z-buffer of the posed mesh) belongs to none of the joint's own body parts
(:func:`~torchmocap.body.parts.own_parts`: an elbow's own skin is in front of it and must not
hide it) and lies more than ``margin`` in front of the joint. A forearm across the chest
hides the chest joints; a hand behind the back is hidden by the torso. Joints outside the image
or behind the camera are reported as not occluded (they are not visible either way; the
detector handles them).

Shapes: ``T`` frames, ``C`` cameras, ``J`` joints, ``V`` vertices, ``F`` faces.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmocap.body.parts import own_parts
from torchmocap.data.synthetic.render import rasterize_zbuffer

__all__ = ["joint_occlusion"]


def joint_occlusion(positions: Tensor, vertices: Tensor, faces: Tensor, face_part: Tensor,
                    parents, rig, margin: float = 0.05, chunk_frames: int = 16) -> Tensor:
    """Which joints the body surface hides from each camera.

    Args:
        positions: ``(T, J, 3)`` world joint centres (m).
        vertices: ``(T, V, 3)`` posed surface vertices (m), same frames.
        faces: ``(F, 3)`` triangle indices into the vertices.
        face_part: ``(F,)`` the joint whose segment carries each face (as
            :class:`~torchmocap.data.synthetic.synthesis.BodySurface`).
        parents: ``J`` parent joint indices (``-1`` for the root).
        rig: :class:`~torchmocap.cameras.CameraRig` with ``C`` cameras.
        margin: metres of surface in front of the joint, beyond its own depth inside the body,
            that count as an occluder (``>= 0``).
        chunk_frames: frames rasterised at once (results do not depend on it).

    Returns:
        ``(T, C, J)`` bool, True where the joint is hidden by the surface.

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> rig = make_ring_rig(1).float()                   # camera 0 at (0, -4, 2.5)
        >>> v = torch.tensor([[[-1., -1, -1], [1, -1, -1], [0, -1, 2]]])  # a wall at y = -1
        >>> f, part = torch.tensor([[0, 1, 2]]), torch.tensor([2])      # carried by joint 2
        >>> joint_occlusion(torch.zeros(1, 2, 3), v, f, part, [-1, 0], rig)[0, 0].tolist()
        Traceback (most recent call last):
        ...
        ValueError: face_part: a part index is not a joint (expected < 2)
        >>> joint_occlusion(torch.zeros(1, 3, 3), v, f, part, [-1, 0, 1], rig)[0, 0].tolist()
        [True, False, False]
    """
    if positions.dim() != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions: expected shape (T, J, 3), got {tuple(positions.shape)}")
    if vertices.dim() != 3 or vertices.shape[-1] != 3 or vertices.shape[0] != positions.shape[0]:
        raise ValueError(f"vertices: expected shape ({positions.shape[0]}, V, 3), got "
                         f"{tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {tuple(faces.shape)}")
    if face_part.shape != faces.shape[:1]:
        raise ValueError(f"face_part: expected shape ({faces.shape[0]},), got "
                         f"{tuple(face_part.shape)}")
    if face_part.numel() and int(face_part.max()) >= positions.shape[1]:
        raise ValueError(f"face_part: a part index is not a joint (expected < "
                         f"{positions.shape[1]})")
    if len(parents) != positions.shape[1]:
        raise ValueError(f"parents: expected {positions.shape[1]} parent indices, got "
                         f"{len(parents)}")
    if not (isinstance(margin, (int, float)) and margin >= 0):
        raise ValueError(f"margin: expected a number >= 0 (metres), got {margin!r}")
    T, J = positions.shape[:2]
    C = rig.num_cameras
    sizes = [tuple(int(x) for x in s) for s in rig.image_size.reshape(-1, 2).tolist()]
    out = torch.zeros(T, C, J, dtype=torch.bool)
    own = torch.cat([own_parts(parents), torch.zeros(J, 1, dtype=torch.bool)], 1)  # +no part
    # cameras of one image size are rasterised together (a rig may mix sizes)
    for size in dict.fromkeys(sizes):
        cams = [c for c, s in enumerate(sizes) if s == size]
        sub = rig if len(cams) == C else rig.subset(cams)
        out[:, cams] = _occluded(positions, vertices, faces, face_part, own, sub, size,
                                 margin, chunk_frames)
    return out


def _occluded(positions, vertices, faces, face_part, own, rig, size, margin, chunk_frames):
    """:func:`joint_occlusion` for a rig whose cameras share the image ``size`` ``(W, H)``."""
    T, J = positions.shape[:2]
    C = rig.num_cameras
    W, H = size
    out = torch.zeros(T, C, J, dtype=torch.bool)
    with torch.no_grad():
        for a in range(0, T, max(1, int(chunk_frames))):
            b = min(T, a + max(1, int(chunk_frames)))
            v = vertices[a:b].to(positions.dtype)
            n = (b - a) * C
            pix, z, _ = rig.project(v)  # (t, C, V, 2), (t, C, V)
            zb = rasterize_zbuffer(pix.reshape(n, -1, 2), z.reshape(n, -1), faces, W, H)
            depth = zb.depth.reshape(b - a, C, H, W)
            jp, jz, jvis = rig.project(positions[a:b])  # (t, C, J, 2), (t, C, J), (t, C, J)
            x = jp[..., 0].round().long().clamp(0, W - 1)
            y = jp[..., 1].round().long().clamp(0, H - 1)
            ti = torch.arange(b - a)[:, None, None].expand_as(x)
            ci = torch.arange(C)[None, :, None].expand_as(x)
            front = depth[ti, ci, y, x]  # (t, C, J) nearest surface at the joint's pixel
            face = zb.face.reshape(b - a, C, H, W)[ti, ci, y, x]
            part = torch.where(face >= 0, face_part[face.clamp_min(0)], J)
            jj = torch.arange(J)[None, None, :].expand_as(part)
            other = (part < J) & ~own[jj, part]
            out[a:b] = jvis & other & (front < jz - margin)
    return out
