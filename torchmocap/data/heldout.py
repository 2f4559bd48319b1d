"""Leave one camera out of tracking, to score the track in it (REFERENCE §11).

A recording loaded with a held-out camera (``load_recording(heldout_camera=...)``, the run
setting ``evaluation.heldout_camera``) holds every view, and ``meta.heldout_camera`` names
the one left out of the other views' masks, the subject fit and the person selection.
:func:`split_heldout` splits it into the sequence a tracker may see (the other views) and
the held-out view (a one-camera sequence) that
:func:`~torchmocap.evaluation.heldout_view_scores` scores the track in. A tracker refuses a
sequence that still holds its held-out camera
(:meth:`~torchmocap.filters.Tracker.check_sequence`).

Example:
    >>> seq = load_recording(path, heldout_camera="cam01")  # doctest: +SKIP
    >>> tracked, heldout = split_heldout(seq)                # doctest: +SKIP
    >>> tracked.rig.names, heldout.rig.names                 # doctest: +SKIP
    (['cam02', 'cam03', 'cam04'], ['cam01'])
"""

from __future__ import annotations

__all__ = ["heldout_camera", "split_heldout"]


def heldout_camera(seq) -> str | None:
    """The name of the held-out camera of ``seq`` (``meta.heldout_camera``) when ``seq``'s
    rig still holds it, else None."""
    name = seq.meta.heldout_camera
    if name is None or seq.rig is None or name not in seq.rig.names:
        return None
    return name


def split_heldout(seq):
    """``(tracked, heldout)``: ``seq`` without its held-out camera and that camera alone
    (:meth:`~torchmocap.data.Sequence.select_cameras`); ``(seq, None)`` when it holds none."""
    name = heldout_camera(seq)
    if name is None:
        return seq, None
    h = seq.rig.names.index(name)
    others = [c for c in range(seq.num_cameras) if c != h]
    return seq.select_cameras(others), seq.select_cameras([h])
