"""evaluate_track on a recording without ground truth: a silhouette IoU far below a fit's is
reported (inverted masks were scored as if nothing were wrong)."""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from torchmocap.assembly import Runtime
from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence
from torchmocap.evaluation import EvaluationWarning, evaluate_track
from torchmocap.filters import FrameInfo, Track


def _scored(root):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loader's own warnings
        seq = load_bodytrack_sequence(root, scale=0.5)
    rt = Runtime.from_sequence(seq)
    theta = torch.as_tensor(seq.meta.initial_poses[:1], dtype=torch.float32)
    return seq, rt, Track(theta=theta, infos=[FrameInfo(0, initial=True)], seconds_per_frame=0.0)


def test_low_silhouette_iou_is_warned(tmp_path, shared_data):
    root = tmp_path / "frame"
    shutil.copytree(shared_data / "multiview" / "bodytrack_sequenceB_1", root)
    seq, rt, track = _scored(root)
    with warnings.catch_warnings():  # the standing start at the hull's centre: no warning
        warnings.simplefilter("error", EvaluationWarning)
        iou = evaluate_track(seq, rt, None, track).metrics["silhouette_iou"]["mean"]
    assert iou > 0.3
    for p in root.glob("FG*/image0000.png"):  # inverted masks
        Image.fromarray(255 - np.asarray(Image.open(p).convert("L"))).save(p)
    seq, rt, track = _scored(root)
    with pytest.warns(EvaluationWarning, match=r"silhouette_iou: the silhouette IoU of the "
                                               r"fitted body is 0\.0\d, far below"):
        m = evaluate_track(seq, rt, None, track).metrics
    assert m["silhouette_iou"]["mean"] < 0.1
