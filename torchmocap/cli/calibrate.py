"""``torchmocap-calibrate``: refine a recording's calibration from the subject's own
detections and write it in the recording's format (Hydra CLI; ``conf/calibrate.yaml``).

The settings are those of ``data=recording`` (``data.path``, ``data.cameras``,
``data.keypoints.*``, ``data.calibration.*``); ``data.calibration.refine`` is implied and the
images are not decoded. Writes ``calibration/`` into the run directory
(:func:`~torchmocap.data.recordings.self_calibration.write_refinement`) and ``metrics.json``
(the refinement's record) last; prints the per-camera table. A failure prints one line on
stderr, writes ``failure.json`` and exits with status 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from torchmocap.cli.runs import console_main, hydra_task

__all__ = ["main", "run"]

_RECORDING = "torchmocap.data.recordings.loader.load_recording"


def run(cfg: DictConfig, out: Path) -> dict:
    """Refine and write; returns the record written to ``out/metrics.json``."""
    from torchmocap.atomic import write_json_atomic
    from torchmocap.cameras import report_markdown, rig_from_dict
    from torchmocap.cli.runs import reported_warnings
    from torchmocap.data.recordings.loader import calibrate_recording
    from torchmocap.data.recordings.self_calibration import write_refinement

    target = cfg.data.get("_target_")
    if target != _RECORDING:
        raise ValueError(f"data: torchmocap-calibrate refines a recording's calibration "
                         f"(data=recording), got a data source {target!r}")
    data = OmegaConf.to_container(cfg.data, resolve=True)
    data.pop("_target_")
    (out / "metrics.json").unlink(missing_ok=True)
    with reported_warnings("torchmocap-calibrate") as warned:
        _, record = calibrate_recording(**data)
        written = write_refinement(out, rig_from_dict(record["rig"]), record,
                                   record["calibration"], record.get("unit"))
    record = {**record, "written": [str(p) for p in written], "warnings": warned}
    write_json_atomic(record, out / "metrics.json")
    print(report_markdown(record["report"]))
    print(f"torchmocap-calibrate: wrote {', '.join(str(p) for p in written)}", file=sys.stderr)
    return record


@hydra.main(config_path="../conf", config_name="calibrate", version_base="1.3")
@hydra_task("torchmocap-calibrate")
def _hydra_main(cfg: DictConfig, out: Path) -> None:
    run(cfg, out)


def main() -> None:
    """Console entry point (exit status 2 when the run failed)."""
    console_main(_hydra_main)


if __name__ == "__main__":
    main()
