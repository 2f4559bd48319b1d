"""Meshes skinned to a skeleton's joints, in the skeleton's rest (zero) pose, for export.

A :class:`MeshSkin` is what a glTF skin needs: vertices of the mesh posed at the skeleton's
zero pose (world, metres, Z up), triangles, and up to four (joint, weight) pairs per vertex,
joints indexed like ``skeleton.joint_names``. Two sources:

* :func:`skin_from_body` — the bundled CC0 body (:class:`~torchmocap.body.SkinnedBody`) bound to
  the skeleton by :meth:`~torchmocap.body.SkinnedBody.bind` (human31-like skeletons; other
  skeletons raise ``ValueError``). The body's linear blend skinning uses per-joint *affine*
  rest alignments (bone-length scaling); a glTF skin wants rigid bind poses (Blender's
  importer cannot keep scaled bones), so the mesh is posed once at the skeleton's zero pose
  by the exact body model and re-skinned rigidly from there: identical at the zero pose and
  at every joint, close to :meth:`~torchmocap.body.SkinnedBody.pose_from_skeleton` elsewhere
  (the two blends differ only where a vertex has several joints).
* :func:`skin_from_parametric` — an Anny body (:class:`~torchmocap.body.ParametricBody`) of a
  phenotype driven by the skeleton's offsets, posed at the zero pose and skinned rigidly the
  same way (its flesh segments' weights summed per carrier joint);
* :func:`stick_figure_skin` — one slim double pyramid per bone, rigidly attached to the bone's
  parent joint: the fallback for any skeleton.

Shapes: ``V`` vertices, ``F`` triangles, ``J`` skeleton joints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["MeshSkin", "skin_from_body", "skin_from_parametric", "stick_figure_skin"]


@dataclass
class MeshSkin:
    """A mesh skinned to skeleton joints.

    Attributes:
        vertices: ``(V, 3)`` float64 rest vertices at the skeleton's zero pose (world, Z up).
        faces: ``(F, 3)`` int64 triangles (counter-clockwise seen from outside).
        joints: ``(V, 4)`` int64 skeleton joint indices.
        weights: ``(V, 4)`` float64 weights, rows summing to 1 (unused slots 0).
        name: label of the mesh (``"body"``, ``"stick_figure"``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    name: str = "mesh"

    def __post_init__(self) -> None:
        V = self.vertices.shape[0]
        if self.vertices.shape != (V, 3) or V == 0:
            raise ValueError(f"vertices: expected (V, 3) with V > 0, got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or \
                (self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V)):
            raise ValueError(f"faces: expected (F, 3) vertex indices in [0, {V}), got shape "
                             f"{self.faces.shape}")
        if self.joints.shape != (V, 4) or self.weights.shape != (V, 4):
            raise ValueError(f"joints, weights: expected ({V}, 4) each, got "
                             f"{self.joints.shape} and {self.weights.shape}")
        s = self.weights.sum(1)
        if (self.weights < 0).any() or not np.allclose(s, 1.0, atol=1e-5):
            raise ValueError("weights: expected non-negative rows summing to 1")


def _top4(dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four largest entries per row of ``(V, K)`` weights, renormalised."""
    K = dense.shape[1]
    if K < 4:
        dense = np.pad(dense, ((0, 0), (0, 4 - K)))
    idx = np.argsort(-dense, axis=1, kind="stable")[:, :4]
    w = np.take_along_axis(dense, idx, axis=1)
    w = np.where(w > 1e-6, w, 0.0)
    total = w.sum(1, keepdims=True)
    if (total <= 0).any():
        raise ValueError("weights: a vertex has no joint with a positive weight")
    idx = np.where(w > 0, idx, 0)
    return idx, w / total


def skin_from_body(body: Any, skeleton: Any) -> MeshSkin:
    """The skinned body bound to ``skeleton``, re-skinned rigidly at its zero pose.

    Args:
        body: a :class:`~torchmocap.body.SkinnedBody`.
        skeleton: the :class:`~torchmocap.skeleton.Skeleton` that drives it.

    Raises:
        ValueError: naming ``skeleton`` when the body cannot be bound to it (joints missing).
    """
    binding = body.bind(skeleton)
    dt = torch.float64
    with torch.no_grad():
        kin0 = skeleton(skeleton.zero_pose(dtype=dt, device=skeleton.offsets.device))
        verts = body.pose_kinematics(kin0, binding)
    dense = binding.weights.detach().cpu().double().numpy()  # (V, Jm)
    idx, w = _top4(dense)
    joint_index = binding.joint_index.detach().cpu().numpy()
    return MeshSkin(vertices=verts.detach().cpu().double().numpy(),
                    faces=body.faces.detach().cpu().numpy().astype(np.int64),
                    joints=joint_index[idx].astype(np.int64), weights=w, name="body")


def skin_from_parametric(body: Any, skeleton: Any, phenotype: Any = None) -> MeshSkin:
    """The Anny ``body`` of ``phenotype`` (``(6,)`` or a dict) driven by ``skeleton``'s offsets,
    at the zero pose, rigidly skinned to its carrier joints.

    Raises:
        ValueError: naming ``skeleton`` when its joints are not the body's.
    """
    if list(skeleton.joint_names) != list(body.joint_names):
        raise ValueError(f"skeleton: expected the Anny body's joints {body.joint_names}, got "
                         f"{list(skeleton.joint_names)}")
    import copy

    dt = torch.float64
    dev = body.template.device
    b64 = copy.deepcopy(body).double()
    with torch.no_grad():
        off = skeleton.offsets.to(dev, dt)
        phen = None if phenotype is None else b64.phenotype_tensor(
            phenotype.to(dt) if isinstance(phenotype, torch.Tensor) else phenotype)
        verts = b64(skeleton.zero_pose(dtype=dt, device=dev), phen, offsets=off).vertices
    J = len(body.joint_names)
    carry = torch.zeros(len(body.segments), J, dtype=dt)
    for g, (c, _) in enumerate(body.segments):
        carry[g, body.joint_names.index(c)] = 1.0
    dense = (body.weights.detach().cpu().double() @ carry).numpy()  # (V, J)
    idx, w = _top4(dense)
    return MeshSkin(vertices=verts.detach().cpu().numpy(),
                    faces=body.faces.detach().cpu().numpy().astype(np.int64),
                    joints=idx.astype(np.int64), weights=w, name="anny_body")


def stick_figure_skin(skeleton: Any, width: float = 0.12, max_radius: float = 0.03) -> MeshSkin:
    """A double pyramid along every bone (parent joint → joint) at the zero pose, each rigidly
    weighted to the parent joint; ``width`` is the pyramid's half-width relative to the bone's
    length (capped at ``max_radius`` metres). Bones shorter than 1 mm are skipped."""
    with torch.no_grad():
        pos = skeleton.joint_positions(skeleton.zero_pose(dtype=torch.float64)).cpu().numpy()
    verts, faces, joints = [], [], []
    for j, q in enumerate(skeleton.parents):
        if q < 0:
            continue
        a, b = pos[q], pos[j]
        axis = b - a
        L = float(np.linalg.norm(axis))
        if L < 1e-3:
            continue
        u = axis / L
        ref = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0.0, 1, 0])
        e1 = np.cross(u, ref)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        r = min(width * L, max_radius)
        mid = a + 0.2 * axis
        ring = [mid + r * (np.cos(k * np.pi / 2) * e1 + np.sin(k * np.pi / 2) * e2)
                for k in range(4)]
        base = len(verts)
        verts += [a, b, *ring]
        for k in range(4):
            r0, r1 = base + 2 + k, base + 2 + (k + 1) % 4
            faces += [[base, r1, r0], [base + 1, r0, r1]]
        joints += [q] * 6
    if not verts:
        raise ValueError("skeleton: no bone longer than 1 mm to draw")
    V = len(verts)
    J = np.zeros((V, 4), np.int64)
    J[:, 0] = joints
    W = np.zeros((V, 4))
    W[:, 0] = 1.0
    return MeshSkin(np.asarray(verts), np.asarray(faces, np.int64), J, W, name="stick_figure")
