"""Leading frames that are not part of the motion: a reference pose before the take.

Some exports start with a pose the subject never held — the cgspeed CMU "MotionBuilder" BVH
files put a synthetic T-pose in frame 0 — and tracking from it starts with a jump of half a
metre. :func:`leading_reference_frames` finds such frames from the motion alone: in the first
``max_frames`` frames, a step (largest displacement of a joint relative to the root between two
frames) far beyond anything the rest of the clip does, at least ``min_jump`` metres and
``factor`` times the 99th percentile of the later steps. Everything up to the last such step is
a reference pose. Fast motion does not trigger it: a kick's largest step is about 1.2 times its
99th percentile, a T-pose frame 0 is 30 times.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["LeadingFrames", "leading_reference_frames", "trim_reference_frames"]


@dataclass(frozen=True)
class LeadingFrames:
    """Result of :func:`leading_reference_frames`.

    Attributes:
        count: leading frames to drop (0: none).
        jump: the largest step among them, metres.
        typical: the 99th percentile of the later steps, metres.
    """

    count: int
    jump: float
    typical: float

    def describe(self) -> str:
        return (f"the first {self.count} frame(s) hold a pose {100 * self.jump:.0f} cm from the "
                f"next (a reference pose: the rest of the clip moves a joint at most "
                f"{100 * self.typical:.1f} cm per frame, 99th percentile)")


def leading_reference_frames(clip, max_frames: int = 5, min_jump: float = 0.15,
                             factor: float = 3.0) -> LeadingFrames:
    """How many leading frames of ``clip`` are a reference pose rather than motion.

    Args:
        clip: a :class:`~torchmocap.io.MotionClip`.
        max_frames: only the first ``max_frames`` steps are examined.
        min_jump: smallest step (metres) that can mark a reference pose.
        factor: the step must also exceed ``factor`` times the 99th percentile of the steps
            after the examined ones.

    Returns:
        :class:`LeadingFrames` (``count`` 0 when the clip has fewer than ``4 * max_frames``
        frames: too short to say what is typical).
    """
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
        raise ValueError(f"max_frames: expected an int >= 1, got {max_frames!r}")
    for name, v in (("min_jump", min_jump), ("factor", factor)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
            raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    T = clip.num_frames
    if T < 4 * max_frames:
        return LeadingFrames(0, 0.0, 0.0)
    p = clip.global_positions().detach().to(torch.float64)
    rel = p - p[:, :1]
    step = (rel[1:] - rel[:-1]).norm(dim=-1).amax(-1)  # (T-1,)
    typical = float(step[max_frames:].quantile(0.99))
    big = (step[:max_frames] > max(min_jump, factor * typical)).nonzero().flatten()
    if big.numel() == 0:
        return LeadingFrames(0, 0.0, typical)
    k = int(big[-1]) + 1
    return LeadingFrames(k, float(step[:k].max()), typical)


def trim_reference_frames(clip, path=None):
    """``(clip without its leading reference frames, LeadingFrames)``; warns when it drops
    any (naming ``path``)."""
    lead = leading_reference_frames(clip)
    if lead.count == 0:
        return clip, lead
    import warnings

    where = f"{path}: " if path is not None else ""
    warnings.warn(f"{where}skipped {lead.describe()} - pass skip_frames=0 "
                  "(data.clip.skip_frames=0) to keep them", stacklevel=3)
    return clip.slice(lead.count), lead
