"""Observation synthesis: a motion and a scenario in, a :class:`~torchmocap.data.Sequence` out.

``synthesize(clip_or_subject, scenario, seed=…)`` renders a *different* body than trackers use
(the skinned CC0 mesh by default, capsules or the Anny parametric body of a phenotype on
request) through the scenario's camera rig:

1. ground truth from :func:`~torchmocap.data.subjects.fit_subject` (exact source joints and bone
   frames, fitted human31 poses), optionally re-centred in the capture volume; with
   ``body: anny`` the fitted poses are retargeted onto the phenotype's own skeleton
   (:func:`retarget_to_anny`), which is then the ground truth's;
2. the posed surface ``(T, V, 3)`` and its faces, each face tagged with a body part;
3. per camera a z-buffer (:mod:`torchmocap.data.synthetic.render`) → filled silhouettes, then
   boundary
   noise, holes, clutter blobs, the floor shadow and dropped views
   (:mod:`torchmocap.data.synthetic.silhouettes`);
4. colour images: part albedo, Lambertian shading, a textured floor/wall background, shadow,
   global illumination change, pixel noise (:mod:`torchmocap.data.synthetic.images`);
5. IMU orientations with device noise, misalignment, desync, drift and drops
   (:mod:`torchmocap.data.imu`); depth point clouds (:mod:`torchmocap.data.depth`); 2D joints
   (:mod:`torchmocap.data.synthetic.joints2d`).

Randomness: one seed; every modality draws from its own generator derived from it, so switching
one modality off or changing its settings leaves the others unchanged, and the same seed gives
an identical sequence.
"""

from __future__ import annotations

import copy
import hashlib
import numbers
import time
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from torchmocap.data.metadata import SequenceMeta
from torchmocap.data.sequence import GroundTruth, Sequence
from torchmocap.data.synthetic.depth import make_depth_camera, synthesize_depth
from torchmocap.data.synthetic.images import (
    background_images,
    illumination_gain,
    part_albedo,
    shade_body,
    to_uint8,
)
from torchmocap.data.synthetic.imu import synthesize_imu
from torchmocap.data.synthetic.joints2d import synthesize_joints2d
from torchmocap.data.synthetic.occlusion import joint_occlusion
from torchmocap.data.synthetic.render import (
    capsule_mesh,
    rasterize_mask,
    rasterize_zbuffer,
    vertex_normals,
)
from torchmocap.data.synthetic.scenario import Scenario, build_rig, load_scenario
from torchmocap.data.synthetic.silhouettes import (
    add_boundary_noise,
    add_clutter,
    drop_views,
    punch_holes,
    shadow_points,
)

__all__ = ["MARKER_PARTS", "BodySurface", "CameraVisibilityError", "SynthesisError",
           "anny_surface", "body_surface", "render_silhouettes", "retarget_to_anny",
           "select_markers", "subgenerator", "synthesize"]


class SynthesisError(ValueError):
    """Synthesis cannot proceed (names the argument at fault)."""


class CameraVisibilityError(SynthesisError):
    """A camera of the rig never sees the body (e.g. a rig looking away)."""


@dataclass
class BodySurface:
    """A posed triangle surface.

    Attributes:
        vertices: ``(T, V, 3)`` world vertices (m).
        faces: ``(F, 3)`` vertex indices.
        face_part: ``(F,)`` index into ``part_names`` (the skeleton joint whose frame carries
            the face).
        part_names: skeleton joint names.
    """

    vertices: Tensor
    faces: Tensor
    face_part: Tensor
    part_names: list[str]


def subgenerator(seed: int, name: str) -> torch.Generator:
    """A ``torch.Generator`` seeded from ``(seed, name)`` (stable across runs and platforms)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise SynthesisError(f"seed: expected an integer, got {seed!r}")
    h = hashlib.sha256(f"{int(seed)}:{name}".encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(h[:8], "little") & ((1 << 63) - 1))


def _slice_subject(subject, frames: int | None):
    if frames is None or frames >= subject.num_frames:
        return subject
    return replace(subject, theta=subject.theta[:frames], positions=subject.positions[:frames],
                   rotations=subject.rotations[:frames], residual=subject.residual[:frames],
                   rotation_residual=subject.rotation_residual[:frames])


_SKINNED: dict[str, Any] = {}
_REFERENCE_WIDTH = 320.0


def _skinned_body():
    if "body" not in _SKINNED:
        from torchmocap.body import SkinnedBody

        _SKINNED["body"] = SkinnedBody()
    return _SKINNED["body"]


def _anny_body(skeleton):
    """A :class:`~torchmocap.body.ParametricBody` driven by ``skeleton`` (the Anny arrays are
    read once per process)."""
    from torchmocap.body import ParametricBody
    from torchmocap.body.anny_model import load_anny_data

    if "anny_data" not in _SKINNED:
        _SKINNED["anny_data"] = load_anny_data()
    try:
        return ParametricBody(skeleton, data=_SKINNED["anny_data"])
    except ValueError as e:
        raise SynthesisError(f"body: the Anny body cannot be driven by this skeleton ({e})") \
            from e


def retarget_to_anny(subject, phenotype: dict[str, float]):
    """The subject's motion on the Anny body of ``phenotype``: its skeleton has the phenotype's
    bone lengths (:meth:`~torchmocap.body.ParametricBody.skeleton_for`), the joint angles are the
    fitted ones and the root translation is scaled by the ratio of the two pelvis heights (a
    child takes a child's steps); joint positions are that skeleton's forward kinematics, the
    bone orientations stay the subject's (the same angles give the same orientations).

    Returns:
        the retargeted :class:`~torchmocap.data.subjects.Subject` and the body
        (:class:`~torchmocap.body.ParametricBody`, float32).
    """
    body = _anny_body(copy.deepcopy(subject.skeleton).float())
    sk = body.skeleton_for(phenotype)
    old = subject.skeleton
    k = float(sk.offsets[0, 2]) / float(old.offsets[0, 2])
    theta = subject.theta.detach().clone()
    theta[:, :3] = theta[:, :3] * k
    sk = sk.to(old.offsets.dtype)
    with torch.no_grad():
        positions = sk(theta.to(old.offsets.dtype)).positions.to(subject.positions.dtype)
    return replace(subject, skeleton=sk, theta=theta, positions=positions), body


def anny_surface(body, skeleton, theta: Tensor, phenotype: dict[str, float], chunk: int = 16
                 ) -> BodySurface:
    """Posed surface of the Anny ``body`` of ``phenotype`` driven by ``skeleton``'s offsets at
    poses ``theta (T, D)``, each face tagged with the skeleton joint carrying most of its
    vertices."""
    names = list(body.joint_names)
    off = skeleton.offsets.to(theta.dtype)
    with torch.no_grad():
        verts = torch.cat([body(theta[a:a + chunk], phenotype, offsets=off).vertices
                           for a in range(0, theta.shape[0], chunk)])
    vpart = body.mesh_parts().cpu()
    faces = body.faces.cpu()
    fp = vpart[faces]
    same12 = fp[:, 1] == fp[:, 2]
    face_part = torch.where(same12 & (fp[:, 0] != fp[:, 1]), fp[:, 1], fp[:, 0])
    return BodySurface(verts.detach(), faces, face_part, names)


def body_surface(skeleton, theta: Tensor, kind: str = "skinned", chunk: int = 64
                 ) -> BodySurface:
    """Posed surface of ``skeleton`` at poses ``theta (T, D)``.

    Args:
        skeleton: a human31-compatible :class:`~torchmocap.skeleton.Skeleton`.
        theta: ``(T, D)`` poses.
        kind: ``skinned`` (bundled CC0 mesh, linear blend skinning) or ``capsules``
            (:class:`~torchmocap.body.CapsuleBody` of the skeleton, meshed).
        chunk: frames posed at once.
    """
    names = list(skeleton.joint_names)
    if kind == "skinned":
        from torchmocap.body.skinning import HUMAN31_BONE_MAP

        body = _skinned_body()
        binding = body.bind(skeleton)  # not cached on the shared body (no growth per call)
        verts = torch.cat([body.pose_kinematics(skeleton(theta[a:a + chunk]), binding)
                           for a in range(0, theta.shape[0], chunk)])
        bone = body.weights.argmax(-1)  # (V,) dominant mesh bone
        joint_of_bone = torch.tensor([names.index(HUMAN31_BONE_MAP[b]) for b in body.bone_names])
        vpart = joint_of_bone[bone]
        faces = body.faces
        # a face belongs to the part of the majority of its vertices (first vertex on ties)
        fp = vpart[faces]
        same12 = fp[:, 1] == fp[:, 2]
        face_part = torch.where(same12 & (fp[:, 0] != fp[:, 1]), fp[:, 1], fp[:, 0])
        return BodySurface(verts, faces, face_part, names)
    if kind == "capsules":
        from torchmocap.body import CapsuleBody

        caps = CapsuleBody(skeleton)
        kin = skeleton(theta)
        ep = caps.endpoints(kin)
        verts, faces, face_cap = capsule_mesh(ep, caps.radii.to(ep.dtype))
        parent = caps.parent_index[face_cap]
        return BodySurface(verts, faces, parent, names)
    raise SynthesisError(f"body: expected 'skinned' or 'capsules', got {kind!r}")


def _standing_height(body, skeleton, phenotype: dict[str, float]) -> float:
    """The Anny body's standing height (m) driven by ``skeleton`` (its rest pose)."""
    with torch.no_grad():
        off = skeleton.offsets.float()
        z = body(skeleton.zero_pose(dtype=off.dtype), phenotype, offsets=off).vertices[..., 2]
    return round(float(z.max() - z.min()), 5)


#: body parts (skeleton joints) that carry the evaluation markers: the arms (Hauberg & Pedersen
#: place their motion-capture markers on the arms)
MARKER_PARTS = ("l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist")


def select_markers(surface: BodySurface, parts=MARKER_PARTS, per_part: int = 6
                   ) -> tuple[Tensor, list[str]]:
    """Vertex indices ``(M,)`` of ``per_part`` markers on each named body part, spread over the
    part by farthest-point sampling on the first frame, and the part of each marker."""
    faces = surface.faces
    V = surface.vertices.shape[1]
    vpart = torch.full((V,), -1, dtype=torch.long)
    vpart[faces.reshape(-1)] = surface.face_part.repeat_interleave(3)
    v0 = surface.vertices[0].double()
    idx, names = [], []
    for p in parts:
        if p not in surface.part_names:
            continue
        cand = (vpart == surface.part_names.index(p)).nonzero()[:, 0]
        if cand.numel() == 0:
            continue
        pts = v0[cand]
        chosen = [int(torch.argmin((pts - pts.mean(0)).norm(dim=-1)))]
        d = (pts - pts[chosen[0]]).norm(dim=-1)
        for _ in range(min(per_part, cand.numel()) - 1):
            k = int(torch.argmax(d))
            chosen.append(k)
            d = torch.minimum(d, (pts - pts[k]).norm(dim=-1))
        idx += cand[chosen].tolist()
        names += [p] * len(chosen)
    return torch.tensor(idx, dtype=torch.long), names


def render_silhouettes(surface: BodySurface, rig, chunk_frames: int | None = None) -> Tensor:
    """Noise-free filled silhouettes ``(T, C, H, W)`` bool of a posed surface."""
    T = surface.vertices.shape[0]
    C = rig.num_cameras
    W, H = int(rig.image_size[0, 0]), int(rig.image_size[0, 1])
    pix, z, _ = rig.project(surface.vertices)
    m = rasterize_mask(pix.reshape(T * C, -1, 2), z.reshape(T * C, -1), surface.faces, W, H)
    return m.reshape(T, C, H, W)


def _check_visibility(positions: Tensor, rig) -> None:
    _, _, vis = rig.project(positions)  # (T, C, J)
    seen = vis.any(-1).any(0)  # (C,)
    if not bool(seen.all()):
        bad = [rig.names[c] for c in range(rig.num_cameras) if not bool(seen[c])]
        raise CameraVisibilityError(
            f"rig: camera(s) {bad} see no joint of the body in any of the {positions.shape[0]} "
            f"frames (looking away or too close?); check the rig's extrinsics / the scenario's "
            f"'rig' and 'center'")


def _compose_images(zb, surface: BodySurface, normals: Tensor, frames: Tensor, rig,
                    background: Tensor, albedo: Tensor, light: Tensor, ambient: float,
                    smooth: bool) -> Tensor:
    """Colour (b, H, W, 3) float of z-buffered images; ``frames (b,)`` frame index per image."""
    b, H, W = zb.face.shape
    C = rig.num_cameras
    cam = torch.arange(b) % C
    img = background[cam].clone()
    loc = zb.mask.nonzero()  # (N, 3): image, y, x
    f = zb.face[loc[:, 0], loc[:, 1], loc[:, 2]]
    lam = zb.bary[loc[:, 0], loc[:, 1], loc[:, 2]].to(normals.dtype)  # (N, 3)
    fr = frames[loc[:, 0]]
    vid = surface.faces[f]  # (N, 3)
    p = (lam[..., None] * surface.vertices[fr[:, None], vid]).sum(1)
    if smooth:
        n = (lam[..., None] * normals[fr[:, None], vid]).sum(1)
    else:
        v = surface.vertices[fr[:, None], vid]
        n = torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n = torch.nn.functional.normalize(n, dim=-1, eps=1e-12)
    centres = rig.camera_centers().to(p.dtype)[cam[loc[:, 0]]]
    rgb = shade_body(n, albedo[f].to(p.dtype), p - centres, light, ambient)
    img[loc[:, 0], loc[:, 1], loc[:, 2]] = rgb.to(img.dtype)
    return img


def synthesize(
    clip_or_subject,
    scenario: str | Scenario = "studio",
    generator: torch.Generator | None = None,
    seed: int | None = None,
    frames: int | None = None,
    skeleton_map: str | None = None,
    chunk_frames: int = 8,
) -> Sequence:
    """Synthesise observations of a motion under a scenario.

    Args:
        clip_or_subject: a :class:`~torchmocap.io.MotionClip` (resampled to the scenario's fps
            and fitted) or a fitted :class:`~torchmocap.data.subjects.Subject` (used at its fps).
        scenario: scenario name, YAML path or :class:`~torchmocap.data.synthetic.scenario.Scenario`.
        generator: source of the seed (one integer is drawn from it) when ``seed`` is None.
        seed: integer seed (default 0 when neither is given).
        frames: synthesise the first ``frames`` frames (default: all).
        skeleton_map: skeleton map for fitting a clip (default: auto-detected).
        chunk_frames: frames rendered at once (memory bound; results do not depend on it).

    Returns:
        a :class:`~torchmocap.data.Sequence` with every enabled modality and ground truth.

    Raises:
        SynthesisError: ``frames < 1`` or an unknown body kind.
        CameraVisibilityError: a camera never sees the body.
        ScenarioError: malformed scenario; SensorPlacementError: unknown sensor bone.
    """
    from torchmocap.data.subjects.mocap import Subject, fit_subject
    from torchmocap.io import MotionClip

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    sc.validate()
    if frames is not None and frames < 1:
        raise SynthesisError(f"frames: expected at least 1 frame, got {frames}")
    if seed is None:
        seed = 0 if generator is None else int(
            torch.randint(0, 2**62, (), generator=generator, dtype=torch.int64))
    elif isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise SynthesisError(f"seed: expected an integer, got {seed!r} (int() would silently "
                             "use another seed)")
    seed = int(seed)
    if isinstance(clip_or_subject, MotionClip):
        clip = clip_or_subject
        if clip.num_frames < 1:
            raise SynthesisError("clip_or_subject: the clip has no frames")
        if abs(clip.fps - sc.fps) > 1e-6:
            clip = clip.resample(sc.fps)
        if frames is not None and frames < clip.num_frames:
            clip = clip.slice(0, frames)
        subject = fit_subject(clip, skeleton_map=skeleton_map)
        timings["fit_s"] = time.perf_counter() - t0
    elif isinstance(clip_or_subject, Subject):
        subject = _slice_subject(clip_or_subject, frames)
    else:
        raise SynthesisError(f"clip_or_subject: expected a MotionClip or a Subject, got "
                             f"{type(clip_or_subject).__name__}")
    if subject.num_frames < 1:
        raise SynthesisError("clip_or_subject: no frames to synthesise")
    anny = phen = None
    if sc.body == "anny":
        from torchmocap.body.phenotypes import resolve_phenotype

        phen = resolve_phenotype(sc.phenotype, sc.phenotype_seed, "scenario.phenotype")
        t1 = time.perf_counter()
        subject, anny = retarget_to_anny(subject, phen)
        timings["retarget_s"] = time.perf_counter() - t1
    T = subject.num_frames
    fps = float(subject.fps)

    # ---- ground truth (optionally re-centred)
    theta = subject.theta.detach().clone()
    sk = subject.skeleton
    if sc.ground_truth == "fitted" or anny is not None:
        # every modality from the fitted human31 pose (the Anny body's positions are its own
        # skeleton's; its bone orientations, below, follow ground_truth)
        with torch.no_grad():
            kin = sk(theta)
        positions, rotations = kin.positions.detach().clone(), kin.rotations.detach().clone()
        if sc.ground_truth == "source":
            rotations = subject.rotations.detach().clone()
    else:  # exact source positions and orientations
        positions = subject.positions.detach().clone()
        rotations = subject.rotations.detach().clone()
    names = list(sk.joint_names)
    if sc.recenter:
        pel = positions[:, names.index("pelvis"), :2].mean(0)
        shift = torch.tensor(sc.center, dtype=positions.dtype) - pel
        positions[..., :2] += shift
        theta[:, :2] += shift.to(theta.dtype)
    gt = GroundTruth(sk.to_dict(), theta, positions, rotations, names)

    rig = build_rig(sc.rig, sc.image_size).float()
    need_rig = sc.silhouettes.enabled or sc.images.enabled or sc.joints2d.enabled
    if need_rig:
        _check_visibility(positions.float(), rig)
    C = rig.num_cameras
    W, H = int(sc.image_size[0]), int(sc.image_size[1])
    light = torch.tensor(sc.light_direction, dtype=torch.float32)
    seq = Sequence(fps=fps, scenario=sc.name, rig=rig, ground_truth=gt,
                   joint_names=names)

    # ---- surface
    t1 = time.perf_counter()
    surface = None
    if need_rig or sc.depth.enabled:
        sk32 = copy.deepcopy(sk).float()  # nn.Module.float() is in place: keep the caller's
        surface = (anny_surface(anny, sk32, theta.float(), phen) if anny is not None else
                   body_surface(sk32, theta.float(), sc.body))
        timings["pose_s"] = time.perf_counter() - t1

    # ---- markers on the observed skin (error measure of Hauberg & Pedersen, eq. 16)
    if surface is not None:
        midx, mparts = select_markers(surface)
        if midx.numel():
            gt.markers = surface.vertices[:, midx].detach().to(positions.dtype).clone()
            gt.marker_parts = mparts

    # ---- silhouettes and images
    dropped = None
    if sc.silhouettes.enabled or sc.images.enabled:
        t1 = time.perf_counter()
        assert surface is not None
        masks = torch.zeros(T, C, H, W, dtype=torch.bool)
        images = torch.zeros(T, C, H, W, 3, dtype=torch.uint8) if sc.images.enabled else None
        want_shadow = sc.silhouettes.shadow or (sc.images.enabled and
                                                sc.images.shadow_darkening > 0)
        shadow = torch.zeros(T, C, H, W, dtype=torch.bool) if want_shadow else None
        g_img = subgenerator(seed, "images")
        if sc.images.enabled:
            bg = background_images(rig, light, sc.images.ambient, seed=int(seed) % 100003)
            gain = illumination_gain(T, fps, sc.images.illumination_change,
                                     sc.images.illumination_period_s, g_img)
            albedo = part_albedo(surface.part_names, surface.face_part)
        for a in range(0, T, chunk_frames):
            b = min(T, a + chunk_frames)
            v = surface.vertices[a:b]
            pix, z, _ = rig.project(v)
            n_img = (b - a) * C
            if sc.images.enabled:
                zb = rasterize_zbuffer(pix.reshape(n_img, -1, 2), z.reshape(n_img, -1),
                                       surface.faces, W, H)
                masks[a:b] = zb.mask.reshape(b - a, C, H, W)
            else:
                masks[a:b] = rasterize_mask(pix.reshape(n_img, -1, 2), z.reshape(n_img, -1),
                                            surface.faces, W, H).reshape(b - a, C, H, W)
            if shadow is not None:
                sp, sz, _ = rig.project(shadow_points(v, light))
                shadow[a:b] = rasterize_mask(sp.reshape(n_img, -1, 2), sz.reshape(n_img, -1),
                                             surface.faces, W, H).reshape(b - a, C, H, W)
            if sc.images.enabled:
                normals = vertex_normals(v, surface.faces) if sc.images.smooth_shading else v
                fr = torch.arange(b - a).repeat_interleave(C)
                img = _compose_images(zb, replace(surface, vertices=v), normals, fr, rig, bg,
                                      albedo, light, sc.images.ambient,
                                      sc.images.smooth_shading)
                img = img.reshape(b - a, C, H, W, 3)
                if shadow is not None and sc.images.shadow_darkening > 0:
                    sh = shadow[a:b] & ~masks[a:b]
                    img = torch.where(sh[..., None], img * (1 - sc.images.shadow_darkening
                                                            * (1 - sc.images.ambient)), img)
                img = img * gain[a:b, None, None, None, None]
                for t in range(a, b):  # one noise stream per frame: independent of chunking
                    images[t] = to_uint8(img[t - a], sc.images.pixel_noise,
                                         subgenerator(seed, f"images/{t}"))
        timings["render_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        g_sil = subgenerator(seed, "silhouettes")
        s = sc.silhouettes
        flat = masks.reshape(T * C, H, W)
        if s.shadow and shadow is not None:
            flat = flat | shadow.reshape(T * C, H, W)
        k = W / _REFERENCE_WIDTH  # corruption sizes are given for 320-px-wide images
        flat = add_boundary_noise(flat, s.boundary_flip, max(1, round(s.boundary_width * k)),
                                  g_sil)
        flat = punch_holes(flat, s.holes, (s.hole_radius[0] * k, s.hole_radius[1] * k), g_sil)
        flat = add_clutter(flat, s.clutter, (s.clutter_radius[0] * k, s.clutter_radius[1] * k),
                           g_sil)
        flat, drop = drop_views(flat, s.drop_view, g_sil)
        dropped = drop.reshape(T, C)
        if images is not None and bool(dropped.any()):
            images[dropped] = 0
        seq.silhouettes = flat.reshape(T, C, H, W) if s.enabled else None
        seq.view_dropped = dropped
        seq.images = images
        timings["corrupt_s"] = time.perf_counter() - t1

    # ---- IMU
    if sc.imu.enabled:
        t1 = time.perf_counter()
        u = sc.imu
        seq.imu = synthesize_imu(rotations, names, dict(u.sensors), list(u.tracking), fps,
                                 subgenerator(seed, "imu"), offset=u.offset, noise=u.noise,
                                 kappa=u.kappa, tangent_std_deg=u.tangent_std_deg,
                                 dof=u.dof, heading_walk_deg=u.heading_walk_deg,
                                 misalignment_deg=u.misalignment_deg,
                                 desync_frames=u.desync_frames,
                                 drift_deg_per_min=u.drift_deg_per_min, drop_prob=u.drop_prob)
        timings["imu_s"] = time.perf_counter() - t1

    # ---- depth
    if sc.depth.enabled:
        t1 = time.perf_counter()
        d = sc.depth
        assert surface is not None
        cam = make_depth_camera(d.position, d.target, d.image_size, d.fov_deg).float()
        _check_visibility(positions.float(), cam)
        seq.depth = synthesize_depth(surface.vertices, surface.faces, cam,
                                     subgenerator(seed, "depth"), noise_std=d.noise_std,
                                     hole_prob=d.hole_prob, holes=d.holes,
                                     hole_radius=tuple(d.hole_radius), max_points=d.max_points)
        timings["depth_s"] = time.perf_counter() - t1

    # ---- 2D joints
    occluded_fraction = None
    if sc.joints2d.enabled:
        j = sc.joints2d
        occluded = None
        if j.occlusion:
            assert surface is not None
            occluded = joint_occlusion(positions.float(), surface.vertices, surface.faces,
                                       surface.face_part, list(sk.parents), rig,
                                       j.occlusion_margin)
        seq.joints2d = synthesize_joints2d(positions.float(), rig, subgenerator(seed, "joints2d"),
                                           j.pixel_noise, j.outlier_prob, j.miss_prob,
                                           tuple(j.confidence), dropped, occluded,
                                           j.occluded_miss_prob, j.occluded_pixel_noise,
                                           tuple(j.occluded_confidence))
        if occluded is not None:
            occluded_fraction = round(float(occluded.float().mean()), 4)
    timings["total_s"] = time.perf_counter() - t0
    seq.meta = SequenceMeta(
        seed=int(seed), scenario=sc.to_dict(), body=sc.body, phenotype=phen,
        body_height=None if anny is None else _standing_height(anny, sk, phen),
        subject={"family": subject.family, "residual_mean_m": float(subject.residual.mean()),
                 "mapped_bones": list(subject.mapped_bones)},
        timings={k: round(v, 4) for k, v in timings.items()},
        joints2d_occluded_fraction=occluded_fraction)
    return seq
