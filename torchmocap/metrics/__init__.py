"""Error metrics: orientation error (Pons-Moll eq. 19), MPJPE."""

from torchmocap.metrics.errors import mpjpe_mm, orientation_error_deg, summarize_errors

__all__ = ["mpjpe_mm", "orientation_error_deg", "summarize_errors"]
