"""Summaries of a track's per-frame diagnostics: refinement statistics, hypotheses as arrays,
frames without evidence and proposal fallbacks (with warnings), the body fit, a smoother's
report without its per-frame parts."""

from __future__ import annotations

import warnings

import pytest

from torchmocap.evaluation import (
    EvaluationWarning,
    hypothesis_arrays,
    smoother_report,
    summarize_diagnostics,
)
from torchmocap.filters import FrameInfo


def test_refine_statistics_are_averaged_over_the_tracked_frames():
    infos = [FrameInfo(0, initial=True),
             FrameInfo(1, refine={"start_energy": 3.0, "final_energy": 1.0, "start": 1}),
             FrameInfo(2, refine={"start_energy": 5.0, "final_energy": 2.0, "start": 0}),
             FrameInfo(3, ess=[4.0])]
    m = summarize_diagnostics(infos)["refine_mean"]
    # frame 0 (the initial pose) is not a tracked frame; frames without a refine stage are
    # not averaged in
    assert m == {"final_energy": 1.5, "start": 0.5, "start_energy": 4.0}


def test_hypothesis_arrays_pad_missing_modes_with_nan():
    import numpy as np

    infos = [FrameInfo(0),
             FrameInfo(1, hypotheses=[[0.1, 0.2], [0.3, 0.4]], hypothesis_weights=[0.7, 0.3],
                       mode_energy=[1.0, 2.0]),
             FrameInfo(2, hypotheses=[[0.5, 0.6]], hypothesis_weights=[1.0], mode_energy=[3.0])]
    a = hypothesis_arrays(infos, 2)
    assert a["hypotheses"].shape == (3, 2, 2) and a["hypotheses"].dtype == np.float32
    np.testing.assert_allclose(a["hypotheses"][1], [[0.1, 0.2], [0.3, 0.4]], rtol=1e-6)
    np.testing.assert_allclose(a["hypotheses"][2, 0], [0.5, 0.6], rtol=1e-6)
    assert np.isnan(a["hypotheses"][2, 1]).all() and np.isnan(a["hypotheses"][0]).all()
    np.testing.assert_allclose(a["hypothesis_weights"][1], [0.7, 0.3], rtol=1e-6)
    np.testing.assert_allclose(a["hypothesis_energy"][2], [3.0, np.nan], rtol=1e-6)
    assert hypothesis_arrays([FrameInfo(0), FrameInfo(1, ess=[1.0])], 2) == {}  # one estimate
    with pytest.raises(ValueError, match=r"infos\[1\]\.hypotheses: expected \(K, 3\)"):
        hypothesis_arrays(infos, 3)


def test_missing_evidence_and_fallbacks_warn():
    infos = [FrameInfo(0, initial=True, seconds=2.5),
             FrameInfo(1, no_evidence=["silhouette"], proposal={"fallback_silhouette": 1.0,
                                                                "tries": 4.0}),
             FrameInfo(2, no_evidence=["silhouette", "depth"],
                       proposal={"fallback_silhouette": 0.0, "tries": 2.0}),
             FrameInfo(3, proposal={"fallback_silhouette": 0.0, "tries": 3.0})]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = summarize_diagnostics(infos)
    assert m["frames_without_evidence"] == {"silhouette": 2, "depth": 1}
    assert m["proposal_mean"]["tries"] == pytest.approx(3.0)
    assert m["seconds_first_frame"] == 2.5
    texts = [str(w.message) for w in caught if w.category is EvaluationWarning]
    assert any("silhouette 2, depth 1" in t for t in texts)
    assert any("fell back" in t and "silhouette 1" in t for t in texts)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert summarize_diagnostics(infos[:1] + infos[3:])["frames_without_evidence"] == {}
    assert not caught


def test_body_fit_summary_over_passes():
    first = FrameInfo(0, initial=True,
                      body_fit={"iou_before": 0.5, "iou_after": 0.6, "energy_before": 3.0,
                                "energy_after": 2.0, "scales": {"knee": 1.1}, "kept": True,
                                "seconds": 1.0},
                      refit=[{"body_fit": {"iou_before": 0.6, "iou_after": 0.7,
                                           "energy_after": 1.5, "scales": {"knee": 1.05},
                                           "total_scales": {"knee": 1.155}, "kept": False,
                                           "seconds": 0.5}}])
    m = summarize_diagnostics([first])["body_fit"]
    assert m["iou_before"] == 0.5 and m["iou_after"] == 0.7 and m["energy_after"] == 1.5
    assert m["passes"] == 2 and m["kept"] == [True, False] and m["seconds"] == 1.5
    assert m["scales"] == {"knee": 1.05} and m["total_scales"] == {"knee": 1.155}


def test_smoother_report_drops_per_frame_parts():
    rep = {"name": "viterbi+kalman", "stages": [{"name": "viterbi", "modes": [0, 1],
                                                  "theta": object()},
                                                 {"name": "kalman", "dofs": {"a": 1}}]}
    out = smoother_report(rep)
    assert out["stages"][0] == {"name": "viterbi"} and out["stages"][1]["dofs"] == {"a": 1}
    assert "modes" in rep["stages"][0]  # the input is left as it was
