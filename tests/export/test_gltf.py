"""Animated GLB export: the file parses back (our reader and trimesh's), the document is
consistent (accessor counts, bounds, buffer length), keyframe times are the frame times, the
joint nodes reproduce the skeleton's forward kinematics at every frame (so the root translation
at frame k is the estimate's), the skinned mesh follows the body model, typed errors, atomic
writes."""

from __future__ import annotations

import json
import logging
import struct

import numpy as np
import pytest
import torch

from torchmocap.body import SkinnedBody
from torchmocap.export import (
    Z_UP_TO_Y_UP,
    gltf_document,
    read_accessor,
    read_glb,
    skin_from_body,
    stick_figure_skin,
    write_glb,
)
from torchmocap.skeleton import human31, upper_body

T, FPS = 6, 25.0


@pytest.fixture(scope="module")
def skeleton():
    return human31()


@pytest.fixture(scope="module")
def body():
    return SkinnedBody()


@pytest.fixture(scope="module")
def thetas(skeleton):
    g = torch.Generator().manual_seed(7)
    th = 0.3 * torch.randn(T, skeleton.num_dofs, generator=g)
    th[:, :3] = torch.cumsum(0.05 * torch.randn(T, 3, generator=g), 0) + torch.tensor(
        [0.2, -0.1, 0.95])
    return th


@pytest.fixture(scope="module")
def glb(tmp_path_factory, skeleton, thetas, body):
    path = write_glb(tmp_path_factory.mktemp("glb") / "walk.glb", skeleton, thetas, FPS,
                     body_mesh=body)
    doc, blob = read_glb(path)
    return path, doc, blob


def _quat_matrix(q):
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _node_globals(doc, blob, k):
    """Global 4x4 transform of every node at keyframe ``k`` (TRS of the node, replaced by the
    animation's sample k where a channel targets it)."""
    nodes = doc["nodes"]
    trs = [{"translation": np.array(n.get("translation", [0, 0, 0]), float),
            "rotation": np.array(n.get("rotation", [0, 0, 0, 1]), float)} for n in nodes]
    anim = doc["animations"][0]
    for ch in anim["channels"]:
        s = anim["samplers"][ch["sampler"]]
        trs[ch["target"]["node"]][ch["target"]["path"]] = read_accessor(doc, blob,
                                                                        s["output"])[k]
    local = []
    for t in trs:
        M = np.eye(4)
        M[:3, :3] = _quat_matrix(t["rotation"])
        M[:3, 3] = t["translation"]
        local.append(M)
    out = [None] * len(nodes)

    def visit(i, parent):
        out[i] = parent @ local[i]
        for c in nodes[i].get("children", []):
            visit(c, out[i])

    for root in doc["scenes"][0]["nodes"]:
        visit(root, np.eye(4))
    return out


class TestWriteGlb:
    def test_smoke_parses_back(self, glb):
        import trimesh

        path, doc, blob = glb
        assert doc["asset"]["version"] == "2.0"
        data = path.read_bytes()
        magic, version, length = struct.unpack_from("<III", data)
        assert (magic, version, length) == (0x46546C67, 2, len(data))
        json.dumps(doc, allow_nan=False)  # strict JSON
        assert doc["buffers"][0]["byteLength"] == len(blob) and len(blob) % 4 == 0
        scene = trimesh.load(path)  # an independent reader
        (mesh,) = scene.geometry.values()
        pos = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
        assert len(mesh.vertices) == doc["accessors"][pos]["count"]

    def test_cardinality(self, glb, skeleton, body):
        _, doc, blob = glb
        J, V, F = len(skeleton.joint_names), body.num_vertices, body.faces.shape[0]
        assert len(doc["nodes"]) == J + 2 and doc["nodes"][0]["name"] == "world"
        assert [n["name"] for n in doc["nodes"][1:J + 1]] == list(skeleton.joint_names)
        for j, p in enumerate(skeleton.parents):  # the hierarchy is the skeleton's
            parent = 0 if p < 0 else 1 + p
            assert 1 + j in doc["nodes"][parent]["children"]
        prim = doc["meshes"][0]["primitives"][0]
        counts = {k: doc["accessors"][a]["count"] for k, a in prim["attributes"].items()}
        assert counts == {"POSITION": V, "NORMAL": V, "JOINTS_0": V, "WEIGHTS_0": V}
        idx = read_accessor(doc, blob, prim["indices"])
        assert idx.size == 3 * F and idx.max() < V
        skin = doc["skins"][0]
        assert skin["joints"] == list(range(1, J + 1))
        assert doc["accessors"][skin["inverseBindMatrices"]]["count"] == J
        joints = read_accessor(doc, blob, prim["attributes"]["JOINTS_0"])
        weights = read_accessor(doc, blob, prim["attributes"]["WEIGHTS_0"])
        assert joints.max() < J
        np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-5)
        pos = read_accessor(doc, blob, prim["attributes"]["POSITION"])
        acc = doc["accessors"][prim["attributes"]["POSITION"]]
        np.testing.assert_allclose(acc["min"], pos.min(0), atol=1e-6)
        np.testing.assert_allclose(acc["max"], pos.max(0), atol=1e-6)

    def test_feature_keyframe_times_are_frame_times(self, glb):
        _, doc, blob = glb
        anim = doc["animations"][0]
        rotated = {ch["target"]["node"] for ch in anim["channels"]
                   if ch["target"]["path"] == "rotation"}
        assert rotated == set(range(1, len(doc["nodes"]) - 1))
        for s in anim["samplers"]:
            times = read_accessor(doc, blob, s["input"])
            np.testing.assert_allclose(times, np.arange(T) / FPS, rtol=1e-6)
            assert doc["accessors"][s["input"]]["count"] == T
            assert doc["accessors"][s["output"]]["count"] == T
            assert s["interpolation"] == "LINEAR"

    def test_feature_root_translation_is_the_estimate(self, glb, skeleton, thetas):
        _, doc, blob = glb
        root = skeleton.parents.index(-1)
        anim = doc["animations"][0]
        (ch,) = [c for c in anim["channels"] if c["target"] == {"node": 1 + root,
                                                                 "path": "translation"}]
        out = read_accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"])
        with torch.no_grad():
            expect = skeleton(thetas.double()).positions[:, root].numpy()
        np.testing.assert_allclose(out, expect, atol=1e-5)
        R_world = _quat_matrix(doc["nodes"][0]["rotation"])
        np.testing.assert_allclose(R_world, Z_UP_TO_Y_UP, atol=1e-7)

    def test_feature_nodes_reproduce_forward_kinematics(self, glb, skeleton, thetas):
        _, doc, blob = glb
        J = len(skeleton.joint_names)
        with torch.no_grad():
            kin = skeleton(thetas.double())
        for k in range(T):
            G = _node_globals(doc, blob, k)
            for j in range(J):
                np.testing.assert_allclose(G[1 + j][:3, :3],
                                           Z_UP_TO_Y_UP @ kin.rotations[k, j].numpy(),
                                           atol=1e-5)
                np.testing.assert_allclose(G[1 + j][:3, 3],
                                           Z_UP_TO_Y_UP @ kin.positions[k, j].numpy(),
                                           atol=1e-5)

    def test_feature_skinned_mesh_follows_the_body_model(self, glb, skeleton, thetas, body):
        """glTF skinning (sum of w_i · joint_matrix_i · IBM_i over the vertex's joints) equals
        the body model's posed vertices where a vertex follows one joint, and stays close
        elsewhere."""
        _, doc, blob = glb
        prim = doc["meshes"][0]["primitives"][0]
        v = read_accessor(doc, blob, prim["attributes"]["POSITION"]).astype(float)
        joints = read_accessor(doc, blob, prim["attributes"]["JOINTS_0"]).astype(int)
        weights = read_accessor(doc, blob, prim["attributes"]["WEIGHTS_0"]).astype(float)
        ibm = read_accessor(doc, blob, doc["skins"][0]["inverseBindMatrices"]).astype(float)
        binding = body.bind(skeleton)
        single = weights.max(1) > 1 - 1e-6
        assert single.sum() > 100
        for k in (0, T - 1):
            G = _node_globals(doc, blob, k)
            mats = np.stack([G[n] @ ibm[i] for i, n in enumerate(doc["skins"][0]["joints"])])
            vh = np.concatenate([v, np.ones((len(v), 1))], 1)
            posed = np.einsum("vk,vkab,vb->va", weights, mats[joints], vh)[:, :3]
            with torch.no_grad():
                ref = body.pose_kinematics(skeleton(thetas[k].double()), binding)
            ref = ref.double().numpy() @ Z_UP_TO_Y_UP.T
            np.testing.assert_allclose(posed[single], ref[single], atol=2e-4)
            assert np.median(np.linalg.norm(posed - ref, axis=1)) < 5e-3

    def test_stick_figure_fallback(self, tmp_path, caplog, body):
        sk = upper_body()
        th = torch.zeros(3, sk.num_dofs)
        with caplog.at_level(logging.WARNING, logger="torchmocap.export.gltf"):
            path = write_glb(tmp_path / "u.glb", sk, th, 10.0, body_mesh=body)
        assert "stick figure" in caplog.text
        doc, _ = read_glb(path)
        assert doc["meshes"][0]["name"] == "stick_figure"
        assert len(doc["nodes"]) == len(sk.joint_names) + 2
        skin = stick_figure_skin(sk)
        assert skin.vertices.shape[0] == doc["accessors"][
            doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["count"]

    def test_up_z_keeps_the_world_axes(self, skeleton, thetas):
        doc, _ = gltf_document(skeleton, thetas, FPS, skin=None, up="z")
        assert "rotation" not in doc["nodes"][0] and "meshes" not in doc

    def test_skin_from_body(self, skeleton, body):
        skin = skin_from_body(body, skeleton)
        with torch.no_grad():
            ref = body.pose_from_skeleton(skeleton, skeleton.zero_pose(dtype=torch.float64))
        np.testing.assert_allclose(skin.vertices, ref.numpy(), atol=1e-9)
        assert skin.joints.shape == (body.num_vertices, 4)

    def test_exception(self, tmp_path, skeleton, thetas):
        path = tmp_path / "x.glb"
        path.write_bytes(b"old")
        bad = thetas.clone()
        bad[2, 5] = float("nan")
        with pytest.raises(ValueError, match="thetas"):
            write_glb(path, skeleton, bad, FPS)
        with pytest.raises(ValueError, match="thetas"):
            write_glb(path, skeleton, thetas[:, :5], FPS)
        for fps in (0, -1.0, float("nan"), True):
            with pytest.raises(ValueError, match="fps"):
                write_glb(path, skeleton, thetas, fps)
        with pytest.raises(ValueError, match="up"):
            write_glb(path, skeleton, thetas, FPS, up="x")
        assert path.read_bytes() == b"old"  # a failed write leaves the old file
        assert sorted(p.name for p in tmp_path.iterdir()) == ["x.glb"]
        with pytest.raises(ValueError, match="path"):
            read_glb(path)
