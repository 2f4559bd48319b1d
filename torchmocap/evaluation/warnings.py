"""The warning category of the evaluation functions."""

from __future__ import annotations

__all__ = ["EvaluationWarning"]


class EvaluationWarning(UserWarning):
    """A score that measures something else than the tracking (held DoFs that the truth moves),
    or frames whose evidence was missing or whose proposal fell back to its prior. The command
    line prints each as ``torchmocap-track: warning: ...``."""
