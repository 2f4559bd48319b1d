"""experiments/body/surface.py and recording.py read their runs: the capsules-vs-surface table
(the lower error marked, the per-group means) and the recording's runs table."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _module(name):
    spec = importlib.util.spec_from_file_location(f"body_{name}",
                                                  ROOT / "experiments" / "body" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _write(d: Path, m: dict) -> None:
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps(m))


def _metrics(mp, ori=5.0, spf=0.7):
    return {"mpjpe_mm": {"mean": mp}, "orientation_error_deg": {"mean": ori},
            "seconds_per_frame": spf}


def test_surface_report(tmp_path):
    mod = _module("surface")
    caps, surf = tmp_path / "caps", tmp_path / "surf"
    _write(caps / "anny_clean" / "heavy" / "walking" / mod.CAPS, _metrics(21.0))
    _write(surf / "anny_clean" / "heavy" / "walking" / mod.SURF, _metrics(15.0))
    _write(caps / "skinned_clean" / "makehuman" / "jumping" / mod.CAPS, _metrics(21.4))
    _write(surf / "skinned_clean" / "makehuman" / "jumping" / mod.SURF, _metrics(23.6))
    # a clip with one tracker only is left out
    _write(caps / "anny_clean" / "tall" / "walking" / mod.CAPS, _metrics(26.0))
    text = mod.report(surf, caps, None)
    assert "| heavy | walking | 21.0 → **15.0** |" in text
    assert "| makehuman | jumping | **21.4** → 23.6 |" in text
    assert "tall" not in text.split("Mean")[0]
    assert "Mean over 2 runs: MPJPE 21.2 → 19.3 mm (lower with the surface term in 1 of 2)" \
        in text
    assert "Anny phenotypes (1 runs): MPJPE 21.0 → 15.0 mm, lower in 1." in text


def test_recording_table(tmp_path):
    mod = _module("recording")
    base = {"seconds_per_frame": 0.5, "silhouette_iou": {"mean": 0.7},
            "heldout": {"camera": "cam01", "silhouette_iou": 0.57, "median_px": 28.8,
                        "mean_px": 31.4, "pck_05": 0.8}}
    _write(tmp_path / "caps_w0", base)
    fit = {"iou_before": 0.74, "iou_after": 0.75, "height": 1.78, "phenotype": {"age": 0.6}}
    _write(tmp_path / "anny_surf", {**base, "body_fit": fit})
    rows = mod.table(tmp_path).splitlines()
    assert len(rows) == 4
    assert rows[2].startswith("| anny_surf | cam01 | Anny fitted | surface points | 100 | 0.570")
    assert rows[3].startswith("| caps_w0 | cam01 | capsules | capsules | 0 | 0.570 | 28.8")
