"""Likelihoods of poses given observations; each returns a log-likelihood per particle.

Silhouette (hard/smooth, Pons-Moll eq. 17 V_silh), appearance (colour consistency, V_app),
sensor orientation (the S of GS/LS).
"""

from torchmocap.likelihoods.appearance import (
    AppearanceLikelihood,
    appearance_energy,
    body_surface_pattern,
)
from torchmocap.likelihoods.orientation import OrientationLikelihood, orientation_energy
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    SilhouetteObservation,
    prepare_silhouettes,
    render_capsule_silhouettes,
    silhouette_energy,
    silhouette_iou,
)

__all__ = [
    "AppearanceLikelihood",
    "OrientationLikelihood",
    "SilhouetteLikelihood",
    "SilhouetteObservation",
    "appearance_energy",
    "body_surface_pattern",
    "orientation_energy",
    "prepare_silhouettes",
    "render_capsule_silhouettes",
    "silhouette_energy",
    "silhouette_iou",
]
