"""Likelihood terms: energies ``V = −log p + const`` of poses given one frame's observations.

The interface (:class:`Likelihood`, :class:`Poses`, :class:`WeightedSum`, :class:`FrameEnergy`)
is in :mod:`torchmocap.likelihoods.base`; terms: multi-view silhouette (hard/smooth, Pons-Moll
eq. 17 V_silh), appearance (colour consistency, V_app), sensor orientation (the S of GS/LS).
"""

from torchmocap.likelihoods.appearance import (
    AppearanceLikelihood,
    ColourObservation,
    appearance_energy,
    body_surface_pattern,
    prepare_images,
)
from torchmocap.likelihoods.base import (
    FrameEnergy,
    Likelihood,
    Poses,
    WeightedSum,
    check_energy,
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
    "ColourObservation",
    "FrameEnergy",
    "Likelihood",
    "OrientationLikelihood",
    "Poses",
    "SilhouetteLikelihood",
    "SilhouetteObservation",
    "WeightedSum",
    "appearance_energy",
    "body_surface_pattern",
    "check_energy",
    "orientation_energy",
    "prepare_images",
    "prepare_silhouettes",
    "render_capsule_silhouettes",
    "silhouette_energy",
    "silhouette_iou",
]
