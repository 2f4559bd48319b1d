"""Animated glTF 2.0 (binary ``.glb``) of a skinned mesh following a skeleton track.

Written with numpy and json only (the format is a JSON document plus one binary buffer; a
dependency would add nothing here). The file opens in Blender (File → Import → glTF 2.0) and in
web viewers (three.js, Babylon.js, https://gltf-viewer.donmccurdy.com).

Document layout:

* node 0 ``"world"``: the change of axes from torchmocap's world (Z up) to glTF's (Y up)
  (``up="y"``; identity with ``up="z"``), parent of the skeleton's root joint;
* nodes ``1 … J``: one per skeleton joint, same names and hierarchy; node ``1 + j`` holds joint
  ``j``'s *local* transform: rotation ``R_parent⁻¹ R_j`` and translation
  ``R_parent⁻¹ (p_j − p_parent)`` (the root: ``R_root``, ``p_root``), so composing the nodes from
  ``"world"`` down reproduces the skeleton's forward kinematics ``(R_j, p_j)``;
* node ``J + 1``: the skinned mesh (identity transform, at the scene root, as the glTF spec
  recommends), its vertices in glTF world coordinates at the skeleton's zero pose;
* skin 0: joints = nodes ``1 … J``, ``inverseBindMatrices[j] = (W · G_j(0))⁻¹`` (``W`` the
  world node, ``G_j(0)`` joint ``j``'s global transform at the zero pose) — rigid;
* animation 0 ``"track"``: one LINEAR rotation channel per joint, and a translation channel
  per joint whose local translation changes over the track (the root; the others are bone
  offsets, constant, stored on the nodes); keyframe times ``t / fps`` seconds.

Shapes: ``T`` frames, ``D`` pose DoF, ``J`` joints.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.export.skins import (
    MeshSkin,
    skin_from_body,
    skin_from_parametric,
    stick_figure_skin,
)

__all__ = [
    "Z_UP_TO_Y_UP",
    "gltf_document",
    "read_accessor",
    "read_glb",
    "write_glb",
]

log = logging.getLogger(__name__)

#: rotation taking torchmocap's Z-up world to glTF's Y-up world: (x, y, z) -> (x, z, -y)
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])

_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPES = {_FLOAT: np.float32, _UBYTE: np.uint8, _USHORT: np.uint16, _UINT: np.uint32}
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


class _Builder:
    """Accumulates bufferViews and accessors over one binary buffer (4-byte aligned)."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            bounds: bool = False) -> int:
        a = np.ascontiguousarray(array, dtype=_DTYPES[component])
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": a.nbytes}
        if target is not None:
            view["target"] = target
        self.blob += a.tobytes()
        self.views.append(view)
        n = _COMPONENTS[kind]
        acc: dict[str, Any] = {"bufferView": len(self.views) - 1, "componentType": component,
                               "count": int(a.size // n), "type": kind}
        if bounds:
            flat = a.reshape(-1, n)
            acc["min"] = [float(v) if component == _FLOAT else int(v) for v in flat.min(0)]
            acc["max"] = [float(v) if component == _FLOAT else int(v) for v in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _quaternions_xyzw(R: np.ndarray) -> np.ndarray:
    """``(T, 3, 3)`` rotations to ``(T, 4)`` unit quaternions in glTF's (x, y, z, w) order,
    signs chosen continuous over time (so LINEAR interpolation takes the short way)."""
    from torchmocap.geometry import matrix_to_quaternion

    q = matrix_to_quaternion(torch.from_numpy(R)).numpy()  # w, x, y, z
    q = np.concatenate([q[:, 1:], q[:, :1]], axis=1)
    for t in range(1, q.shape[0]):
        if float(np.dot(q[t], q[t - 1])) < 0:
            q[t] = -q[t]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _homogeneous(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    M = np.zeros((*R.shape[:-2], 4, 4))
    M[..., :3, :3] = R
    M[..., :3, 3] = p
    M[..., 3, 3] = 1.0
    return M


def _check_track(skeleton: Any, thetas: Any, fps: float) -> Tensor:
    th = torch.as_tensor(thetas).detach()
    D = skeleton.num_dofs
    if th.dim() == 1:
        th = th[None]
    if th.dim() != 2 or th.shape[1] != D or th.shape[0] < 1:
        raise ValueError(f"thetas: expected a track (T, {D}) with T >= 1, got "
                         f"{tuple(th.shape)}")
    if not bool(torch.isfinite(th).all()):
        raise ValueError("thetas: expected finite values, found NaN or inf")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or \
            not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite number > 0, got {fps!r}")
    return th.to("cpu", torch.float64)


def gltf_document(skeleton: Any, thetas: Any, fps: float, skin: MeshSkin | None = None,
                  up: str = "y", name: str = "torchmocap") -> tuple[dict, bytes]:
    """The glTF JSON document and its binary buffer for a skeleton track (see module doc).

    Args:
        skeleton: the :class:`~torchmocap.skeleton.Skeleton` of the track.
        thetas: poses ``(T, D)`` (radians; root translation in metres).
        fps: frame rate; keyframe ``t`` is at ``t / fps`` seconds.
        skin: the mesh to skin (:mod:`torchmocap.export.skins`); None: joints only.
        up: ``"y"`` (glTF convention, default) or ``"z"`` (torchmocap's world axes as they are).

    Returns:
        ``(document, buffer)``; ``document["buffers"][0]["byteLength"] == len(buffer)``.
    """
    th = _check_track(skeleton, thetas, fps)
    if up not in ("y", "z"):
        raise ValueError(f"up: expected 'y' or 'z', got {up!r}")
    W = Z_UP_TO_Y_UP if up == "y" else np.eye(3)
    parents = list(skeleton.parents)
    names = list(skeleton.joint_names)
    J = len(names)
    with torch.no_grad():
        kin = skeleton(th)
        kin0 = skeleton(torch.zeros(1, skeleton.num_dofs, dtype=torch.float64))
    R = kin.rotations.cpu().numpy()  # (T, J, 3, 3)
    p = kin.positions.cpu().numpy()  # (T, J, 3)
    T = R.shape[0]
    R_loc, t_loc = np.empty_like(R), np.empty_like(p)
    for j, q in enumerate(parents):
        if q < 0:
            R_loc[:, j], t_loc[:, j] = R[:, j], p[:, j]
        else:
            Rq_T = np.swapaxes(R[:, q], -1, -2)
            R_loc[:, j] = Rq_T @ R[:, j]
            t_loc[:, j] = (Rq_T @ (p[:, j] - p[:, q])[..., None])[..., 0]

    b = _Builder()
    world = {"name": "world", "children": [1 + parents.index(-1)]}
    if up == "y":
        world["rotation"] = _quaternions_xyzw(W[None])[0].tolist()
    nodes: list[dict] = [world]
    quats = [_quaternions_xyzw(R_loc[:, j]) for j in range(J)]
    for j in range(J):
        node: dict[str, Any] = {"name": names[j], "translation": t_loc[0, j].tolist(),
                                "rotation": quats[j][0].tolist()}
        kids = [1 + c for c, q in enumerate(parents) if q == j]
        if kids:
            node["children"] = kids
        nodes.append(node)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": f"{name} (torchmocap.export)"},
        "scene": 0, "scenes": [{"name": name, "nodes": [0]}], "nodes": nodes,
    }
    if skin is not None:
        G0 = _homogeneous(kin0.rotations[0].cpu().numpy(), kin0.positions[0].cpu().numpy())
        W4 = _homogeneous(W, np.zeros(3))
        ibm = np.linalg.inv(W4[None] @ G0)  # (J, 4, 4)
        verts = skin.vertices @ W.T
        normals = _vertex_normals(skin.vertices, skin.faces) @ W.T
        attrs = {"POSITION": b.add(verts, _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True),
                 "NORMAL": b.add(normals, _FLOAT, "VEC3", _ARRAY_BUFFER),
                 "JOINTS_0": b.add(skin.joints, _UBYTE if J < 256 else _USHORT, "VEC4",
                                   _ARRAY_BUFFER),
                 "WEIGHTS_0": b.add(skin.weights, _FLOAT, "VEC4", _ARRAY_BUFFER)}
        indices = b.add(skin.faces.reshape(-1), _UINT, "SCALAR", _ELEMENT_ARRAY_BUFFER,
                        bounds=True)
        ibm_acc = b.add(np.swapaxes(ibm, -1, -2).reshape(-1), _FLOAT, "MAT4")  # column-major
        doc["materials"] = [{"name": f"{skin.name}_material",
                             "doubleSided": skin.name != "body",
                             "pbrMetallicRoughness": {
                                 "baseColorFactor": [0.80, 0.62, 0.52, 1.0],
                                 "metallicFactor": 0.0, "roughnessFactor": 0.8}}]
        doc["meshes"] = [{"name": skin.name, "primitives": [
            {"attributes": attrs, "indices": indices, "material": 0, "mode": 4}]}]
        doc["skins"] = [{"name": "skeleton", "joints": list(range(1, J + 1)),
                         "inverseBindMatrices": ibm_acc, "skeleton": 1 + parents.index(-1)}]
        nodes.append({"name": skin.name, "mesh": 0, "skin": 0})
        doc["scenes"][0]["nodes"].append(len(nodes) - 1)
    times = b.add(np.arange(T, dtype=np.float64) / float(fps), _FLOAT, "SCALAR", bounds=True)
    samplers, channels = [], []
    for j in range(J):
        samplers.append({"input": times, "output": b.add(quats[j], _FLOAT, "VEC4"),
                         "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1,
                         "target": {"node": 1 + j, "path": "rotation"}})
        if np.abs(t_loc[:, j] - t_loc[:1, j]).max() > 1e-7:
            samplers.append({"input": times, "output": b.add(t_loc[:, j], _FLOAT, "VEC3"),
                             "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1,
                             "target": {"node": 1 + j, "path": "translation"}})
    doc["animations"] = [{"name": "track", "samplers": samplers, "channels": channels}]
    while len(b.blob) % 4:
        b.blob.append(0)
    doc["accessors"] = b.accessors
    doc["bufferViews"] = b.views
    doc["buffers"] = [{"byteLength": len(b.blob)}]
    return doc, bytes(b.blob)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)`` (``+z`` where a vertex has no face)."""
    v = vertices[faces]  # (F, 3, 3)
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), np.array([0.0, 0.0, 1.0]))


def _glb_bytes(doc: dict, blob: bytes) -> bytes:
    js = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()
    js += b" " * (-len(js) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return b"".join([struct.pack("<III", _GLB_MAGIC, 2, total),
                     struct.pack("<II", len(js), _JSON_CHUNK), js,
                     struct.pack("<II", len(blob), _BIN_CHUNK), blob])


def read_glb(path: str | Path) -> tuple[dict, bytes]:
    """The JSON document and binary chunk of a ``.glb`` file.

    Raises:
        ValueError: naming ``path`` when the file is not a glTF 2.0 binary.
    """
    data = Path(path).read_bytes()
    if len(data) < 20:
        raise ValueError(f"path: {path} is too short for a GLB file")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError(f"path: {path} is not a glTF 2.0 binary (magic {magic:#x}, version "
                         f"{version}, length {length} of {len(data)} bytes)")
    n, kind = struct.unpack_from("<II", data, 12)
    if kind != _JSON_CHUNK:
        raise ValueError(f"path: {path}: the first chunk is not JSON")
    doc = json.loads(data[20:20 + n])
    blob = b""
    off = 20 + n
    if off + 8 <= len(data):
        m, kind = struct.unpack_from("<II", data, off)
        if kind == _BIN_CHUNK:
            blob = data[off + 8:off + 8 + m]
    return doc, blob


def read_accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """Accessor ``index`` of a document as an array ``(count, components)`` (``(count,)`` for
    scalars; matrices as ``(count, 4, 4)`` in row-major order)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    n = _COMPONENTS[acc["type"]]
    dtype = np.dtype(_DTYPES[acc["componentType"]])
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    a = np.frombuffer(blob, dtype=dtype, count=acc["count"] * n, offset=start)
    if acc["type"] == "SCALAR":
        return a.copy()
    if acc["type"] == "MAT4":
        return np.swapaxes(a.reshape(-1, 4, 4), -1, -2).copy()  # stored column-major
    return a.reshape(-1, n).copy()


def write_glb(path: str | Path, skeleton: Any, thetas: Any, fps: float,
              body_mesh: Any = None, up: str = "y", phenotype: Any = None) -> Path:
    """Write an animated GLB of ``skeleton`` following ``thetas``, atomically.

    Args:
        path: output ``.glb`` file.
        skeleton: the track's :class:`~torchmocap.skeleton.Skeleton`.
        thetas: poses ``(T, D)``.
        fps: frame rate of the track (keyframe times ``t / fps``).
        body_mesh: a :class:`~torchmocap.body.SkinnedBody` or an Anny
            :class:`~torchmocap.body.ParametricBody` (of ``phenotype``, driven by the
            skeleton's offsets: e.g. a body fit's) to skin to the skeleton, or None for a stick
            figure. A body that cannot be bound to this skeleton (joints the body
            needs are missing) falls back to the stick figure, with a warning in the log.
        up: ``"y"`` (glTF's convention, default) or ``"z"``.

    Returns:
        the written path.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> write_glb("/tmp/walk.glb", sk, sk.zero_pose((10,)), fps=25.0)  # doctest: +SKIP
    """
    from torchmocap.atomic import atomic_path

    th = _check_track(skeleton, thetas, fps)
    skin = None
    if body_mesh is not None:
        try:
            from torchmocap.body import ParametricBody

            skin = (skin_from_parametric(body_mesh, skeleton, phenotype)
                    if isinstance(body_mesh, ParametricBody) else
                    skin_from_body(body_mesh, skeleton))
        except ValueError as e:
            log.warning("glb: the body mesh cannot be bound to skeleton %r (%s); writing an "
                        "animated stick figure instead", getattr(skeleton, "name", "?"), e)
    if skin is None:
        skin = stick_figure_skin(skeleton)
    doc, blob = gltf_document(skeleton, th, fps, skin=skin, up=up)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(_glb_bytes(doc, blob))
    return path
