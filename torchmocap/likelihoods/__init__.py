"""Likelihood terms: energies ``V = −log p + const`` of poses given one frame's observations.

The interface (:class:`Likelihood`, :class:`Poses`, :class:`WeightedSum`, :class:`FrameEnergy`)
is in :mod:`torchmocap.likelihoods.base`; terms: multi-view silhouette (hard/smooth, Pons-Moll
eq. 17 V_silh), appearance (colour consistency, V_app), sensor orientation (the S of GS/LS),
2D joints and a detector's keypoints (robust reprojection);
learned terms (:mod:`~torchmocap.likelihoods.learned`: features at the projected body, a CNN on
soft renderings), trained by ``torchmocap-train``.
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
from torchmocap.likelihoods.depth import PointCloudLikelihood, point_cloud_energy
from torchmocap.likelihoods.joints2d import (
    ROBUST_COSTS,
    EmptyEvidenceError,
    Joints2DLikelihood,
    Joints2DObservation,
    joints2d_energy,
    occlusion_energy,
    predicted_hidden,
    robust_cost,
)
from torchmocap.likelihoods.keypoints import KeypointLikelihood
from torchmocap.likelihoods.keypoints_learned import LearnedKeypointLikelihood
from torchmocap.likelihoods.learned import (
    ArchitectureMismatchError,
    LearnedLikelihood,
    WeightsError,
)
from torchmocap.likelihoods.learned_features import LearnedFeatureLikelihood
from torchmocap.likelihoods.learned_render import LearnedRenderLikelihood, soft_render_capsules
from torchmocap.likelihoods.limits import JointLimitLikelihood, limit_excess
from torchmocap.likelihoods.orientation import OrientationLikelihood, orientation_energy
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    SilhouetteObservation,
    prepare_silhouettes,
    render_capsule_silhouettes,
    silhouette_energy,
    silhouette_iou,
    soft_capsule_silhouettes,
)
from torchmocap.likelihoods.silhouette_noise import SilhouetteNoiseLikelihood, fit_noise_model
from torchmocap.likelihoods.surface import (
    SurfaceSilhouetteLikelihood,
    surface_samples,
    surface_silhouette_energy,
)

__all__ = [
    "AppearanceLikelihood",
    "ArchitectureMismatchError",
    "ColourObservation",
    "EmptyEvidenceError",
    "FrameEnergy",
    "Joints2DLikelihood",
    "JointLimitLikelihood",
    "Joints2DObservation",
    "KeypointLikelihood",
    "LearnedFeatureLikelihood",
    "LearnedKeypointLikelihood",
    "LearnedLikelihood",
    "LearnedRenderLikelihood",
    "Likelihood",
    "OrientationLikelihood",
    "PointCloudLikelihood",
    "Poses",
    "ROBUST_COSTS",
    "SilhouetteLikelihood",
    "SilhouetteNoiseLikelihood",
    "SilhouetteObservation",
    "SurfaceSilhouetteLikelihood",
    "WeightedSum",
    "WeightsError",
    "appearance_energy",
    "body_surface_pattern",
    "check_energy",
    "fit_noise_model",
    "joints2d_energy",
    "occlusion_energy",
    "predicted_hidden",
    "limit_excess",
    "orientation_energy",
    "point_cloud_energy",
    "prepare_images",
    "prepare_silhouettes",
    "render_capsule_silhouettes",
    "robust_cost",
    "silhouette_energy",
    "silhouette_iou",
    "soft_capsule_silhouettes",
    "soft_render_capsules",
    "surface_samples",
    "surface_silhouette_energy",
]
