"""The smoother interface (``Smoother.smooth(track) -> track``, applied to a finished track) and
:class:`SmootherChain`, smoothers applied one after the other (``smoother=viterbi_kalman``: the
mode sequence first, then the Kalman smoother removes the jitter left within it). The smoothers:
:class:`~torchmocap.filters.ViterbiSmoother` and :class:`~torchmocap.filters.KalmanSmoother`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

from torch import nn

__all__ = ["Smoother", "SmootherChain"]


class Smoother(nn.Module):
    """Base class: ``smooth(track) -> track`` with the smoothed ``theta`` and the filtered
    estimates in ``track.filtered``."""

    def check(self, inference) -> None:
        """Raise ``ValueError`` when ``inference`` does not record what this smoother reads
        (called when a tracker is assembled, before any frame is tracked)."""

    def smooth(self, track):
        raise NotImplementedError


class SmootherChain(Smoother):
    """Smoothers applied one after the other: each stage smooths the previous stage's track.

    Args:
        stages: the smoothers, in order — a sequence, or a mapping ``name -> smoother`` (its
            order is the order of application; Hydra configs compose stages by name, e.g.
            ``conf/smoother/viterbi_kalman.yaml``).

    The returned track's ``filtered`` is the tracker's own estimates (those the first stage
    received), ``theta`` the last stage's output; its ``smoother`` report is
    ``{"name": "a+b", "stages": [report of a, report of b]}``, each stage's report with its
    output track under ``theta`` (``torchmocap-track`` writes each stage's errors to
    ``metrics.json`` instead: an ablation of the stages in one run). Every stage's ``check``
    sees the tracker's inference (a later stage still receives the frames' ``infos``, e.g. the
    hypotheses a Viterbi stage reads).
    """

    def __init__(self, stages: Sequence[Smoother] | Mapping[str, Smoother]) -> None:
        super().__init__()
        items = list(stages.values()) if isinstance(stages, Mapping) else stages
        if isinstance(items, (str, bytes)) or not isinstance(items, Sequence) or not items:
            raise ValueError(f"stages: expected a non-empty sequence or mapping of smoothers, "
                             f"got {stages!r}")
        names = (list(stages.keys()) if isinstance(stages, Mapping)
                 else [str(i) for i in range(len(items))])
        for name, st in zip(names, items):
            if not isinstance(st, Smoother):
                raise TypeError(f"stages[{name!r}]: expected a Smoother, got "
                                f"{type(st).__name__}")
            if isinstance(st, SmootherChain):
                raise TypeError(f"stages[{name!r}]: a chain inside a chain; list its stages "
                                "instead")
        self.stages = nn.ModuleList(items)

    def check(self, inference) -> None:
        for st in self.stages:
            st.check(inference)

    def smooth(self, track):
        filtered = track.filtered if track.filtered is not None else track.theta
        reports = []
        out = track
        for st in self.stages:
            out = st.smooth(out)
            reports.append({**(out.smoother or {"name": type(st).__name__}),
                            "theta": out.theta})
        report = {"name": "+".join(str(r.get("name", "?")) for r in reports),
                  "changed_frames": int((out.theta != filtered).any(-1).sum()),
                  "stages": reports}
        return dataclasses.replace(out, filtered=filtered, smoother=report)
