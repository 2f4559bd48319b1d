"""``torchmocap-synth``: synthesise an observation :class:`~torchmocap.data.Sequence` (Hydra).

Overrides: ``data.clip.path`` (null = the bundled CMU 131_01 walk), ``data.clip.asf``,
``data.clip.skeleton_map``, ``data.clip.frames``, ``data.clip.start``, ``data.clip.skip_frames``,
``data.clip.fps``, ``data.scenario`` (name or YAML path, see
:func:`~torchmocap.data.synthetic.load_scenario`), ``data.scenario_overrides``, ``seed``.
Writes ``sequence/`` (manifest.json, arrays.npz, PNG masks and images) and ``preview.png`` into
the Hydra run directory. Unreadable clips or bad settings: one line on stderr, exit status 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from torchmocap.assembly import load_sequence
from torchmocap.cli.runs import console_main, hydra_task

__all__ = ["main", "preview_image", "run"]


def run(cfg: Any, out_dir: Path) -> dict[str, Any]:
    """Load the clip, fit the subject, synthesise, save ``out_dir/sequence`` and the preview."""
    from torchmocap.data.synthetic.clips import DataConfigError, check_seed

    check_seed(cfg.seed, "seed")  # 1.5 is an error, not seed 1
    t = cfg.get("preview_frame")
    if t is not None and (isinstance(t, bool) or not isinstance(t, int)):
        raise DataConfigError(f"preview_frame: expected a frame index or null, got {t!r}")
    seq = load_sequence(cfg, min_frames=1)
    seq.save(out_dir / "sequence", overwrite=True)
    out = {"sequence": str(out_dir / "sequence"), "frames": seq.num_frames,
           "modalities": seq.modalities}
    if cfg.get("preview", True):
        t = seq.num_frames // 2 if t is None else t
        if not -seq.num_frames <= t < seq.num_frames:
            raise DataConfigError(f"preview_frame: {t} is outside the {seq.num_frames} frames")
        preview_image(seq, t).save(out_dir / "preview.png")
        out["preview"] = str(out_dir / "preview.png")
    return out


def preview_image(seq, t: int):
    """Contact sheet (PIL image) of frame ``t``: per camera the colour view with the 2D joints,
    the silhouette, and the depth points seen from the depth camera."""
    import numpy as np
    from PIL import Image, ImageDraw

    f = seq.frame(t)
    C = seq.num_cameras
    W, H = (int(seq.rig.image_size[0, 0]), int(seq.rig.image_size[0, 1])) if C else (160, 120)
    tiles = []
    for c in range(C):
        if f.images is not None:
            col = Image.fromarray(f.images[c].numpy(), "RGB")
        else:
            col = Image.new("RGB", (W, H))
        if f.joints2d is not None:
            d = ImageDraw.Draw(col)
            for u, v, conf in f.joints2d[c].tolist():
                if conf > 0:
                    r = 2
                    d.ellipse([u - r, v - r, u + r, v + r],
                              outline=(0, 255, 0) if conf >= 0.5 else (255, 200, 0))
        row = [col]
        if f.silhouettes is not None:
            m = f.silhouettes[c].numpy().astype(np.uint8) * 255
            row.append(Image.fromarray(m, "L").convert("RGB"))
        tiles.append(row)
    if seq.depth is not None:
        cam = seq.depth.camera
        dw, dh = int(cam.image_size[0, 0]), int(cam.image_size[0, 1])
        pts = f.depth.float()
        canvas = np.zeros((dh, dw, 3), np.uint8)
        if pts.shape[0]:
            pix, z, vis = cam.project(pts)
            pix, z, vis = pix[0], z[0], vis[0]
            uv = pix[vis].round().long()
            zz = z[vis]
            g = (255 * (1 - (zz - zz.min()) / (zz.max() - zz.min() + 1e-9))).clamp(40, 255)
            canvas[uv[:, 1].clamp(0, dh - 1), uv[:, 0].clamp(0, dw - 1)] = \
                g.byte().numpy()[:, None]
        img = Image.fromarray(canvas, "RGB").resize((W, H), Image.NEAREST)
        tiles.append([img])
    # cameras are columns (colour view on top, silhouette below); the depth view comes last
    nrow = max(len(col) for col in tiles) if tiles else 1
    sheet = Image.new("RGB", (max(1, len(tiles)) * W, nrow * H), (30, 30, 30))
    for j, col in enumerate(tiles):
        for i, im in enumerate(col):
            sheet.paste(im.resize((W, H)), (j * W, i * H))
    ImageDraw.Draw(sheet).text((4, 4), f"{seq.scenario} frame {t}", fill=(255, 255, 0))
    return sheet


@hydra.main(config_path="../conf", config_name="synth", version_base="1.3")
@hydra_task("torchmocap-synth")
def _hydra_main(cfg: DictConfig, out: Path) -> None:
    import json

    (out / "failure.json").unlink(missing_ok=True)
    print(json.dumps(run(cfg, out)))


def main() -> None:
    """Console entry point (exit status 2 when the run, or any job of a sweep, failed)."""
    console_main(_hydra_main)


if __name__ == "__main__":
    main()
