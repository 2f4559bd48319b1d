"""Mask cache: content keys, the PNG folder round trip, hits, misses and atomic writes."""

from __future__ import annotations

import json

import pytest
import torch

from torchmocap.data.recordings.masks import (
    MaskError,
    MaskSettings,
    cached_masks,
    content_key,
    read_mask_folder,
    write_mask_folder,
)


def _masks(T=3, C=2, H=17, W=23, seed=0):
    return torch.rand(T, C, H, W, generator=torch.Generator().manual_seed(seed)) < 0.3


class TestContentKey:
    def test_feature(self, tmp_path):
        a = tmp_path / "a.bin"
        a.write_bytes(b"video bytes")
        k = content_key(a, {"x": 1, "y": [1.0, None]}, torch.arange(4))
        assert len(k) == 32
        # a file is hashed by content: a renamed copy has the same key
        b = tmp_path / "b.bin"
        b.write_bytes(b"video bytes")
        assert content_key(b, {"y": [1.0, None], "x": 1}, torch.arange(4)) == k
        b.write_bytes(b"video bytez")
        assert content_key(b, {"x": 1, "y": [1.0, None]}, torch.arange(4)) != k
        # types and shapes matter, not only values
        assert content_key(torch.arange(4.0)) != content_key(torch.arange(4))
        assert content_key(torch.zeros(2, 3)) != content_key(torch.zeros(3, 2))
        assert content_key(1) != content_key(1.0) != content_key("1")
        assert content_key(MaskSettings()) != content_key(MaskSettings(scale=0.5))

    def test_exception(self, tmp_path):
        with pytest.raises(MaskError, match="is not a readable file"):
            content_key(tmp_path / "missing.mp4")
        with pytest.raises(MaskError, match="cannot hash a object"):
            content_key(object())


class TestMaskFolder:
    def test_feature_round_trip(self, tmp_path):
        m = _masks()
        write_mask_folder(tmp_path / "e", m, {"a": [1, 2]})
        assert (tmp_path / "e" / "cam1" / "00002.png").is_file()
        from PIL import Image

        with Image.open(tmp_path / "e" / "cam0" / "00000.png") as im:
            assert im.mode == "1"  # 1-bit
        back, report = read_mask_folder(tmp_path / "e")
        assert torch.equal(back, m) and report == {"a": [1, 2]}

    def test_exception(self, tmp_path):
        with pytest.raises(MaskError, match=r"masks: expected a \(T, C, H, W\) bool"):
            write_mask_folder(tmp_path / "x", _masks().float())
        with pytest.raises(MaskError, match="report: expected JSON-safe"):
            write_mask_folder(tmp_path / "x", _masks(), {"t": torch.zeros(1)})
        assert not (tmp_path / "x").exists()
        write_mask_folder(tmp_path / "e", _masks())
        (tmp_path / "e" / "cam1" / "00001.png").unlink()
        with pytest.raises(MaskError, match=r"cam1/00001\.png: cannot read mask"):
            read_mask_folder(tmp_path / "e")
        (tmp_path / "e" / "manifest.json").write_text("{")
        with pytest.raises(MaskError, match="manifest.json: not a mask manifest"):
            read_mask_folder(tmp_path / "e")


class TestCachedMasks:
    def test_feature_hit_and_miss(self, tmp_path):
        calls = []

        def compute(seed):
            def fn():
                calls.append(seed)
                return _masks(seed=seed), {"seed": seed}
            return fn

        m1, r1 = cached_masks(tmp_path, ("clip", MaskSettings()), compute(1))
        m2, r2 = cached_masks(tmp_path, ("clip", MaskSettings()), compute(2))
        assert calls == [1] and torch.equal(m1, m2) and r2["seed"] == 1
        assert (r1["cache"]["hit"], r2["cache"]["hit"]) == (False, True)
        m3, r3 = cached_masks(tmp_path, ("clip", MaskSettings(threshold=5.0)), compute(3))
        assert calls == [1, 3] and not torch.equal(m3, m1)
        entries = sorted(p.name for p in tmp_path.iterdir())
        assert entries == sorted([f"masks-{r1['cache']['key']}", f"masks-{r3['cache']['key']}"])

    def test_feature_damaged_entry_is_recomputed(self, tmp_path):
        fn = lambda: (_masks(), {})
        _, r = cached_masks(tmp_path, "k", fn)
        entry = tmp_path / f"masks-{r['cache']['key']}"
        (entry / "cam0" / "00000.png").write_bytes(b"not a png")
        with pytest.warns(UserWarning, match="unreadable.*recomputing"):
            m, r2 = cached_masks(tmp_path, "k", fn)
        assert not r2["cache"]["hit"] and torch.equal(m, _masks())
        assert torch.equal(read_mask_folder(entry)[0], _masks())
        assert [p.name for p in tmp_path.iterdir()] == [entry.name]  # no leftovers

    def test_exception_leaves_nothing(self, tmp_path):
        def broken():
            raise RuntimeError("decoder failed")

        with pytest.raises(RuntimeError, match="decoder failed"):
            cached_masks(tmp_path, "k", broken)
        with pytest.raises(MaskError, match="compute_fn: expected"):
            cached_masks(tmp_path, "k", lambda: (torch.zeros(2, 2), {}))
        with pytest.raises(MaskError, match="report: expected JSON-safe"):
            cached_masks(tmp_path, "k", lambda: (_masks(), {"x": float("nan")}))
        assert list(tmp_path.iterdir()) == []

    def test_feature_manifest(self, tmp_path):
        _, r = cached_masks(tmp_path, "k", lambda: (_masks(), {"n": 1}))
        manifest = json.loads((tmp_path / f"masks-{r['cache']['key']}" / "manifest.json")
                              .read_text())
        assert manifest["format"] == "torchmocap-masks" and manifest["shape"] == [3, 2, 17, 23]
