"""The surface term against the capsule path on the body control clips: report of the runs.

    export OMP_NUM_THREADS=1
    for t in default_anny default_anny_surface; do
      torchmocap-track +experiment=body/control data=anny_clean \\
          data.scenario_overrides.phenotype=heavy data/clip=walking tracker=$t \\
          hydra.run.dir=RUNS/heavy_walking_$t
      torchmocap-track +experiment=body/control data=skinned_clean data/clip=walking \\
          tracker=$t hydra.run.dir=RUNS/makehuman_walking_$t
    done
    python experiments/body/surface.py RUNS

``RUNS/<body>_<clip>_<tracker>/metrics.json``; writes ``results/surface.md``: MPJPE, validation
orientation error and seconds per tracked frame of the fitted body's capsules
(``default_anny``) and of its posed surface points (``default_anny_surface``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent / "results" / "surface.md"
TRACKERS = ("default_anny", "default_anny_surface")


def report(runs: Path) -> str:
    rows = ["| body | clip | MPJPE mm, capsules → surface | orientation °, capsules → surface "
            "| s / frame, capsules → surface |", "|---|---|---|---|---|"]
    keys = sorted({p.name.rsplit("_default_anny", 1)[0] for p in runs.iterdir()
                   if (p / "metrics.json").is_file()})
    for key in keys:
        m = [runs / f"{key}_{t}" / "metrics.json" for t in TRACKERS]
        if not all(f.is_file() for f in m):
            continue
        a, b = (json.loads(f.read_text()) for f in m)
        body, clip = key.split("_", 1)
        rows.append(f"| {body} | {clip} | {a['mpjpe_mm']['mean']:.1f} → "
                    f"{b['mpjpe_mm']['mean']:.1f} | {a['orientation_error_deg']['mean']:.2f} → "
                    f"{b['orientation_error_deg']['mean']:.2f} | "
                    f"{a['seconds_per_frame']:.3f} → {b['seconds_per_frame']:.3f} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    from torchmocap.atomic import write_text_atomic

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", type=Path)
    a = p.parse_args(argv)
    text = report(a.runs)
    write_text_atomic(OUT, "# The surface term vs the capsules of the fitted Anny body\n\n"
                      "Body control clips, clean scenario, synthesis seed 0, 30 frames, the "
                      "default tracker (LS) with the body fitted at the first frame "
                      "(`tracker=default_anny`) and with its silhouette term on the fitted "
                      "body's 400 posed surface points (`tracker=default_anny_surface`); one "
                      "thread on a loaded shared 2-core machine.\n\n" + text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
