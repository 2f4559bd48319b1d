"""The surface term against the capsule path on the body control clips: report of the runs.

    export OMP_NUM_THREADS=1
    # the surface term (tracker=default_anny), every body and clip of the control:
    torchmocap-track -m +experiment=body/control data=anny_clean \\
        data.scenario_overrides.phenotype=child,heavy,slim,tall,female tracker=default_anny
    torchmocap-track -m +experiment=body/control data=skinned_clean tracker=default_anny
    # the capsule path (tracker=default_anny_capsules), into CAPSULES:
    torchmocap-track -m +experiment=body/control data=anny_clean \\
        data.scenario_overrides.phenotype=child,heavy,slim,tall,female \\
        tracker=default_anny_capsules hydra.sweep.dir=CAPSULES
    torchmocap-track -m +experiment=body/control data=skinned_clean \\
        tracker=default_anny_capsules hydra.sweep.dir=CAPSULES
    python experiments/body/surface.py --capsules CAPSULES [--paired PAIRED]

Runs ``<data>/<body>/<clip>/<tracker>/metrics.json`` under ``--surface`` (default
``runs/control``) and ``--capsules``; ``--paired``: a folder of ``<body>_<clip>_<tracker>``
runs of both trackers made one after the other (their times compare; the sweeps' were made on
another day's load). Writes ``results/surface.md``: MPJPE, validation orientation error and
seconds per tracked frame of the fitted body's capsules (``default_anny_capsules``) and of its
posed surface points (``default_anny``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
BODIES = (("anny_clean", "child"), ("anny_clean", "heavy"), ("anny_clean", "slim"),
          ("anny_clean", "tall"), ("anny_clean", "female"), ("skinned_clean", "makehuman"))
CLIPS = ("walking", "jumping", "basketball")
CAPS, SURF = "default_anny_capsules", "default_anny"


def _read(f: Path) -> dict | None:
    return json.loads(f.read_text()) if f.is_file() else None


def _cells(a: dict, b: dict) -> str:
    return (f"{a['mpjpe_mm']['mean']:.1f} → **{b['mpjpe_mm']['mean']:.1f}** | "
            f"{a['orientation_error_deg']['mean']:.2f} → "
            f"{b['orientation_error_deg']['mean']:.2f} | "
            f"{a['seconds_per_frame']:.3f} → {b['seconds_per_frame']:.3f}")


def report(surface: Path, capsules: Path, paired: Path | None) -> str:
    head = ("| body | clip | MPJPE mm, capsules → surface | orientation °, capsules → surface "
            "| s / frame, capsules → surface |\n|---|---|---|---|---|")
    rows, mp, ori, spf = [head], ([], []), ([], []), ([], [])
    for data, body in BODIES:
        for clip in CLIPS:
            a = _read(capsules / data / body / clip / CAPS / "metrics.json")
            b = _read(surface / data / body / clip / SURF / "metrics.json")
            if a is None or b is None:
                continue
            rows.append(f"| {body} | {clip} | {_cells(a, b)} |")
            for acc, key in ((mp, "mpjpe_mm"), (ori, "orientation_error_deg")):
                acc[0].append(a[key]["mean"])
                acc[1].append(b[key]["mean"])
            spf[0].append(a["seconds_per_frame"])
            spf[1].append(b["seconds_per_frame"])
    n = len(mp[0])
    if n:
        def mean(x):
            return sum(x) / len(x)

        better = sum(y < x for x, y in zip(*mp))
        rows += ["", f"Mean over {n} runs: MPJPE {mean(mp[0]):.1f} → {mean(mp[1]):.1f} mm "
                 f"(lower with the surface term in {better} of {n}), orientation "
                 f"{mean(ori[0]):.2f} → {mean(ori[1]):.2f}°, s/frame {mean(spf[0]):.3f} → "
                 f"{mean(spf[1]):.3f} (the two sweeps on different days' load)."]
    if paired is not None:
        rows += ["", "Paired runs (one after the other, the same load):", "", head]
        for body in ("heavy", "makehuman", "tall"):
            for clip in CLIPS:
                a = _read(paired / f"{body}_{clip}_{CAPS}" / "metrics.json")
                b = _read(paired / f"{body}_{clip}_{SURF}" / "metrics.json")
                if a is not None and b is not None:
                    rows.append(f"| {body} | {clip} | {_cells(a, b)} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    from torchmocap.atomic import write_text_atomic

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--surface", type=Path, default=HERE / "runs" / "control")
    p.add_argument("--capsules", type=Path, required=True)
    p.add_argument("--paired", type=Path, default=None)
    a = p.parse_args(argv)
    text = report(a.surface, a.capsules, a.paired)
    write_text_atomic(HERE / "results" / "surface.md",
                      "# The surface term vs the capsules of the fitted Anny body\n\n"
                      "Body control clips, clean scenario, synthesis seed 0, 30 frames, the "
                      "default tracker (LS) with the body fitted at the first frame and its "
                      "silhouette term on the fitted capsules (`tracker=default_anny_capsules`) "
                      "or on 400 posed surface points of the fitted mesh "
                      "(`tracker=default_anny`); one thread on a loaded shared 2-core "
                      "machine.\n\n" + text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
