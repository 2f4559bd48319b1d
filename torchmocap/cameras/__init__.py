"""Camera rigs (OpenCV conventions, on kornia), calibration I/O (our rig files, Pose2Sim/anipose
TOML, OpenCV intri/extri YAML, Bouguet .cal), triangulation and visual-hull carving."""

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
from torchmocap.cameras.rig import (
    CameraError,
    CameraRig,
    estimate_up_direction,
    make_ceiling_rig,
    make_ring_rig,
)
from torchmocap.cameras.triangulation import triangulate_dlt, triangulate_robust

__all__ = [
    "UNITS",
    "CameraError",
    "CameraRig",
    "VisualHull",
    "backproject_pixels",
    "bouguet_calibration_files",
    "calibration_files",
    "camera_centers",
    "camera_key",
    "concat_rigs",
    "distort_normalized",
    "estimate_up_direction",
    "intrinsics_matrix",
    "largest_component",
    "load_rig_file",
    "look_at",
    "make_ceiling_rig",
    "make_ring_rig",
    "max_monotonic_radius",
    "project_points",
    "project_points_planar",
    "read_bouguet_cal",
    "read_bouguet_folder",
    "read_bouguet_rig",
    "read_calibration",
    "read_opencv_calibration",
    "read_rig",
    "read_toml_calibration",
    "rig_from_dict",
    "rig_to_dict",
    "triangulate_dlt",
    "triangulate_robust",
    "visual_hull",
    "world_to_camera",
    "write_rig",
]
