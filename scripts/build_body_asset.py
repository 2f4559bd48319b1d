"""Regenerate torchmocap/assets/body/makehuman_cc0_decimated.npz from the shared CC0 mesh.

Usage: python scripts/build_body_asset.py [--source ../shared/data/body/makehuman_cc0]
       [--target-vertices 4500]. Needs `pip install fast-simplification` (build time only).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchmocap.body.asset_build import build_body_asset

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--source", type=Path,
                    default=ROOT.parent / "shared" / "data" / "body" / "makehuman_cc0")
    ap.add_argument("--out", type=Path,
                    default=ROOT / "torchmocap" / "assets" / "body" / "makehuman_cc0_decimated.npz")
    ap.add_argument("--target-vertices", type=int, default=4500)
    args = ap.parse_args()
    print(build_body_asset(args.source, args.out, args.target_vertices))


if __name__ == "__main__":
    main()
