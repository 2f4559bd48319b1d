"""Error metrics: orientation error (Pons-Moll eq. 19), MPJPE, marker-to-skin distance
(Hauberg & Pedersen eq. 16)."""

from torchmocap.metrics.errors import mpjpe_mm, orientation_error_deg, summarize_errors
from torchmocap.metrics.skin import marker_skin_distance

__all__ = ["marker_skin_distance", "mpjpe_mm", "orientation_error_deg", "summarize_errors"]
