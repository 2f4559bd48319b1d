"""Build the bundled skinned-body asset from the MakeHuman/MPFB2 CC0 base mesh.

Only this builder reads the source folder (``shared/data/body/makehuman_cc0``); the package loads
the result, ``torchmocap/assets/body/makehuman_cc0_decimated.npz``, and never the source.

Source facts (checked on the files): ``base.obj`` is Y-up in decimetres, quads; vertices 0–13379
are the skin, the rest helper geometry (eyes, teeth, hair/skirt helpers) and 8-vertex joint cubes
whose vertex means mark joint centres (``basemesh_vertex_groups.json``); ``rig.cmu_mb.json`` is a
31-bone rig named like the CMU MotionBuilder BVH (each bone's head/tail named by a joint cube, or
by a mean of listed vertices); ``weights.cmu_mb.json`` holds linear-blend-skinning weights.

Conversion to the torchmocap world (Z-up metres, facing −y, left at +x):
``(x, y, z)_mesh / 10 → (x, −z, y)``. Quads are split into triangles; the skin is decimated by
quadric edge collapse (``fast_simplification``, needed only to rebuild) and each decimated vertex
takes the LBS weights of its nearest source skin vertex (top 4 bones, renormalised). Weights on
the opposite side's bones (0.5% on 11 source vertices) are dropped.

Run ``python scripts/build_body_asset.py`` to regenerate.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["SKIN_VERTEX_COUNT", "build_body_asset", "load_makehuman_source", "mesh_to_world"]

#: vertices 0..13379 of base.obj are the skin
SKIN_VERTEX_COUNT = 13380


def mesh_to_world(v: np.ndarray) -> np.ndarray:
    """MakeHuman mesh frame (Y-up, decimetres) → torchmocap world (Z-up metres): (x, −z, y)/10."""
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v[..., 0], -v[..., 2], v[..., 1]], -1) / 10.0


def _read_obj(path: Path) -> tuple[np.ndarray, list[list[int]]]:
    verts, faces = [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                faces.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    return np.asarray(verts, dtype=np.float64), faces


def _group_vertices(groups: dict, name: str) -> np.ndarray:
    idx = [np.arange(a, b + 1) for a, b in groups[name]]
    return np.concatenate(idx)


def load_makehuman_source(source_dir: str | Path) -> dict:
    """Full-resolution skin in world units with dense weights and joint centres.

    Returns a dict: ``vertices (V, 3)``, ``faces (F, 3)`` triangles, ``weights (V, Bn)``,
    ``bone_names``, ``bone_parents`` (index, −1 root), ``bone_heads``/``bone_tails (Bn, 3)``,
    ``joint_names``/``joint_centres (Jc, 3)`` (every joint cube's vertex mean).
    """
    src = Path(source_dir)
    raw, faces = _read_obj(src / "base.obj")
    groups = json.loads((src / "basemesh_vertex_groups.json").read_text())
    rig = json.loads((src / "rig.cmu_mb.json").read_text())
    weights = json.loads((src / "weights.cmu_mb.json").read_text())["weights"]

    world = mesh_to_world(raw)
    joint_names = sorted(k for k in groups if k.startswith("joint-"))
    centres = np.stack([world[_group_vertices(groups, k)].mean(0) for k in joint_names])
    cube = dict(zip(joint_names, centres))

    def end(spec: dict) -> np.ndarray:
        if "cube_name" in spec:
            return cube[spec["cube_name"]]
        return world[np.asarray(spec["vertex_indices"])].mean(0)

    # bones in parent-before-child order
    names: list[str] = []
    pending = dict(rig)
    while pending:
        for n in sorted(pending):
            p = pending[n]["parent"]
            if not p or p in names:
                names.append(n)
                del pending[n]
                break
        else:
            raise ValueError(f"rig.cmu_mb.json: cyclic or dangling parents among {sorted(pending)}")
    parents = [names.index(rig[n]["parent"]) if rig[n]["parent"] else -1 for n in names]
    heads = np.stack([end(rig[n]["head"]) for n in names])
    tails = np.stack([end(rig[n]["tail"]) for n in names])

    V = SKIN_VERTEX_COUNT
    skin_faces = [f for f in faces if max(f) < V]
    tris = []
    for f in skin_faces:
        for k in range(1, len(f) - 1):
            tris.append([f[0], f[k], f[k + 1]])
    W = np.zeros((V, len(names)))
    for b, lst in weights.items():
        for vi, w in lst:
            if vi < V:
                W[vi, names.index(b)] += w
    _drop_cross_side_weights(W, names, world[:V])
    return {"vertices": world[:V], "faces": np.asarray(tris, dtype=np.int64), "weights": W,
            "bone_names": names, "bone_parents": np.asarray(parents), "bone_heads": heads,
            "bone_tails": tails, "joint_names": joint_names, "joint_centres": centres}


def _side(bone: str) -> int:
    if bone.startswith("Left") or bone in ("LHipJoint", "LThumb"):
        return 1
    if bone.startswith("Right") or bone in ("RHipJoint", "RThumb"):
        return -1
    return 0


def _drop_cross_side_weights(W: np.ndarray, names: list[str], vertices: np.ndarray,
                             margin: float = 0.03) -> int:
    """Zero weights of left bones on vertices clearly on the right (x < −margin) and vice versa.

    The source weights give 11 vertices (knees, feet, a hand; x ≈ ±0.2 m) a 0.5% weight on the
    opposite side's bone, so bending one knee would nudge the other. Rows are renormalised in
    place; returns how many weights were dropped.
    """
    side = np.array([_side(n) for n in names])
    x = vertices[:, 0]
    bad = ((x[:, None] < -margin) & (side[None, :] == 1)) | \
        ((x[:, None] > margin) & (side[None, :] == -1))
    bad &= W > 0
    W[bad] = 0.0
    W /= W.sum(1, keepdims=True)
    return int(bad.sum())


def _top_k(W: np.ndarray, k: int = 4) -> tuple[np.ndarray, np.ndarray]:
    idx = np.argsort(-W, axis=1)[:, :k]
    w = np.take_along_axis(W, idx, 1)
    s = w.sum(1, keepdims=True)
    if np.any(s <= 0):
        raise ValueError(f"{int((s <= 0).sum())} vertices have no skinning weight")
    return idx, w / s


def build_body_asset(source_dir: str | Path, out_path: str | Path,
                     target_vertices: int = 4500) -> dict:
    """Decimate the CC0 skin and write the compact ``.npz`` asset; returns summary numbers."""
    import fast_simplification
    from scipy.spatial import cKDTree

    full = load_makehuman_source(source_dir)
    V0 = full["vertices"]
    F0 = full["faces"]
    # a closed triangle mesh has F ≈ 2V
    pts, tris = fast_simplification.simplify(V0, F0.astype(np.int32),
                                             target_count=2 * target_vertices)
    used = np.unique(tris)
    remap = -np.ones(len(pts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    pts, tris = pts[used], remap[tris]
    _, nearest = cKDTree(V0).query(pts)
    idx, w = _top_k(full["weights"][nearest])
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        vertices=pts.astype(np.float32),
        faces=tris.astype(np.int32),
        weight_indices=idx.astype(np.uint8),
        weights=w.astype(np.float32),
        bone_names=np.asarray(full["bone_names"]),
        bone_parents=full["bone_parents"].astype(np.int16),
        bone_heads=full["bone_heads"].astype(np.float32),
        bone_tails=full["bone_tails"].astype(np.float32),
        joint_names=np.asarray(full["joint_names"]),
        joint_centres=full["joint_centres"].astype(np.float32),
        source_vertex_count=np.asarray(len(V0)),
    )
    return {"vertices": len(pts), "faces": len(tris), "source_vertices": len(V0),
            "source_faces": len(F0), "bytes": out.stat().st_size}
