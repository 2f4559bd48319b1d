"""The surface term against the capsule path on the body control clips: report of the runs.

    export OMP_NUM_THREADS=1
    # the capsule path (tracker=default_anny) is the control sweep's (runs/control); the
    # surface term (tracker=default_anny_surface), every body and clip, into SURFACE:
    torchmocap-track -m +experiment=body/control data=anny_clean \\
        data.scenario_overrides.phenotype=child,heavy,slim,tall,female \\
        tracker=default_anny_surface hydra.sweep.dir=SURFACE
    torchmocap-track -m +experiment=body/control data=skinned_clean \\
        tracker=default_anny_surface hydra.sweep.dir=SURFACE
    python experiments/body/surface.py --surface SURFACE [--paired PAIRED]

Runs ``<data>/<body>/<clip>/<tracker>/metrics.json`` under ``--capsules`` (default
``runs/control``) and ``--surface``; ``--paired``: a folder of ``<body>_<clip>_<tracker>``
runs of both trackers made one after the other (their times compare; the sweeps' were made
under other loads). Writes ``results/surface.md``: MPJPE, validation orientation error and
seconds per tracked frame of the fitted body's capsules (``default_anny``) and of its posed
surface points (``default_anny_surface``).
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
CAPS, SURF = "default_anny", "default_anny_surface"


def _read(f: Path) -> dict | None:
    return json.loads(f.read_text()) if f.is_file() else None


def _cells(a: dict, b: dict) -> str:
    x, y = a["mpjpe_mm"]["mean"], b["mpjpe_mm"]["mean"]
    x_, y_ = (f"{x:.1f}", f"**{y:.1f}**") if y < x else (f"**{x:.1f}**", f"{y:.1f}")
    return (f"{x_} → {y_} | "
            f"{a['orientation_error_deg']['mean']:.2f} → "
            f"{b['orientation_error_deg']['mean']:.2f} | "
            f"{a['seconds_per_frame']:.3f} → {b['seconds_per_frame']:.3f}")


def report(surface: Path, capsules: Path, paired: Path | None) -> str:
    head = ("| body | clip | MPJPE mm, capsules → surface | orientation °, capsules → surface "
            "| s / frame, capsules → surface |\n|---|---|---|---|---|")
    rows, mp, ori, spf = [head], ([], []), ([], []), ([], [])
    group: dict[str, tuple[list, list]] = {}
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
            g = group.setdefault("MakeHuman mesh" if body == "makehuman" else "Anny phenotypes",
                                 ([], []))
            g[0].append(a["mpjpe_mm"]["mean"])
            g[1].append(b["mpjpe_mm"]["mean"])
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
                 f"{mean(spf[1]):.3f} (the two sweeps under different loads)."]
        rows += [f"{name} ({len(g[0])} runs): MPJPE {mean(g[0]):.1f} → {mean(g[1]):.1f} mm, "
                 f"lower in {sum(y < x for x, y in zip(*g))}." for name, g in group.items()]
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
    p.add_argument("--capsules", type=Path, default=HERE / "runs" / "control")
    p.add_argument("--surface", type=Path, required=True)
    p.add_argument("--paired", type=Path, default=None)
    a = p.parse_args(argv)
    text = report(a.surface, a.capsules, a.paired)
    write_text_atomic(HERE / "results" / "surface.md",
                      "# The surface term vs the capsules of the fitted Anny body\n\n"
                      "Body control clips, clean scenario, synthesis seed 0, 30 frames, the "
                      "default tracker (LS) with the body fitted at the first frame and its "
                      "silhouette term on the fitted capsules (`tracker=default_anny`) "
                      "or on 400 posed surface points of the fitted mesh "
                      "(`tracker=default_anny_surface`); one thread on a loaded shared 2-core "
                      "machine.\n\n" + text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
