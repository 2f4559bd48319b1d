"""Camera rigs (OpenCV conventions, on kornia), calibration I/O (our rig files, Pose2Sim/anipose
TOML, OpenCV intri/extri YAML, Bouguet .cal), triangulation and visual-hull carving, and the
refinement of a rig (and per-camera time offsets) from the subject's own 2D detections.

Refining a calibration without a board::

    res = bundle_adjust(detections, rig, groups=("rotation", "translation", "focal",
                                                 "time_offset"), frames=(0, 60))
    res.rig                      # the refined CameraRig (for every frame)
    res.time_offsets             # (C,) frames
    print(res.markdown())        # per camera: changes ± std, residuals before -> after
    write_calibration(res.rig, "calibration/Calib_refined.toml")

The pieces a model-based objective reuses: :class:`RigParametrization` (groups, the gauge,
the map to cameras), :class:`RigPriors`, :class:`RobustLoss`, :func:`reprojection_residuals`
and :func:`reprojection_loss` (3D points as a tensor or a callable of the cameras' times),
:class:`RigRefinement` (the parameters as an ``nn.Module``).
"""

from torchmocap.cameras.bundle_adjustment import BundleAdjustmentResult, bundle_adjust
from torchmocap.cameras.calibration import (
    UNITS,
    load_rig_file,
    read_bouguet_cal,
    read_bouguet_rig,
    read_rig,
    rig_from_dict,
    rig_to_dict,
    write_rig,
)
from torchmocap.cameras.calibration_report import refinement_report, report_markdown
from torchmocap.cameras.calibration_writers import (
    write_calibration,
    write_opencv_calibration,
    write_toml_calibration,
)
from torchmocap.cameras.formats import (
    bouguet_calibration_files,
    calibration_files,
    camera_key,
    concat_rigs,
    read_bouguet_folder,
    read_calibration,
    read_opencv_calibration,
    read_toml_calibration,
)
from torchmocap.cameras.hull import VisualHull, largest_component, visual_hull
from torchmocap.cameras.projection import (
    backproject_pixels,
    camera_centers,
    distort_normalized,
    intrinsics_matrix,
    look_at,
    max_monotonic_radius,
    project_points,
    project_points_planar,
    world_to_camera,
)
from torchmocap.cameras.reprojection import (
    RigRefinement,
    RobustLoss,
    interpolate_in_time,
    prior_loss,
    refinement_pixels,
    reprojection_loss,
    reprojection_residuals,
)
from torchmocap.cameras.rig import (
    CameraError,
    CameraRig,
    estimate_up_direction,
    make_ceiling_rig,
    make_ring_rig,
)
from torchmocap.cameras.rig_gauge import gauge_constraints
from torchmocap.cameras.rig_parameters import (
    PARAMETER_NAMES,
    RIG_GROUPS,
    RefinementError,
    RigParametrization,
    apply_rig_parameters,
)
from torchmocap.cameras.rig_priors import RigPriors
from torchmocap.cameras.triangulation import triangulate_dlt, triangulate_robust

__all__ = [
    "PARAMETER_NAMES",
    "RIG_GROUPS",
    "UNITS",
    "BundleAdjustmentResult",
    "CameraError",
    "CameraRig",
    "RefinementError",
    "RigParametrization",
    "RigPriors",
    "RigRefinement",
    "RobustLoss",
    "VisualHull",
    "apply_rig_parameters",
    "backproject_pixels",
    "bouguet_calibration_files",
    "bundle_adjust",
    "calibration_files",
    "camera_centers",
    "camera_key",
    "concat_rigs",
    "distort_normalized",
    "estimate_up_direction",
    "gauge_constraints",
    "interpolate_in_time",
    "intrinsics_matrix",
    "largest_component",
    "load_rig_file",
    "look_at",
    "make_ceiling_rig",
    "make_ring_rig",
    "max_monotonic_radius",
    "project_points",
    "prior_loss",
    "project_points_planar",
    "read_bouguet_cal",
    "read_bouguet_folder",
    "read_bouguet_rig",
    "read_calibration",
    "read_opencv_calibration",
    "read_rig",
    "read_toml_calibration",
    "refinement_pixels",
    "refinement_report",
    "report_markdown",
    "reprojection_loss",
    "reprojection_residuals",
    "rig_from_dict",
    "rig_to_dict",
    "triangulate_dlt",
    "triangulate_robust",
    "visual_hull",
    "world_to_camera",
    "write_calibration",
    "write_opencv_calibration",
    "write_rig",
    "write_toml_calibration",
]
