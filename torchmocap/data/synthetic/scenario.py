"""Scenarios: how observations are synthesised and corrupted (``clean``, ``studio``, ``outdoor``).

A :class:`Scenario` is a typed dataclass tree loaded from ``torchmocap/conf/scenario/<name>.yaml``
(or any YAML path) by :func:`load_scenario`, with keyword overrides (nested dicts or dotted
keys)::

    sc = load_scenario("outdoor", fps=30, imu={"kappa": 300}, **{"silhouettes.holes": 0})

The tracker and the ``torchmocap-synth`` CLI resolve the config string ``data.scenario`` through
it (Hydra cannot switch a nested group with ``data.scenario=outdoor``, so it is a name or path).

Camera rigs (``rig``): the name of a rig config (``ring4`` → ``conf/rig/ring4.yaml``, searched in
the package's ``conf/rig`` and the repository's top-level ``conf/rig``), a path to a rig YAML
(``_target_`` factory config) or calibration file (:func:`~torchmocap.cameras.read_rig`), or an
inline mapping (``_target_`` factory config or a :func:`~torchmocap.cameras.rig_from_dict`
description). The scenario's ``image_size`` overrides the rig's (intrinsics are rescaled).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "MAX_FPS",
    "SENSOR_BONES",
    "TRACKING_SENSORS",
    "DepthConfig",
    "ImageConfig",
    "ImuConfig",
    "Joints2DConfig",
    "Scenario",
    "ScenarioError",
    "SilhouetteConfig",
    "build_rig",
    "known_scenarios",
    "load_scenario",
    "scenario_dir",
]

#: the highest frame rate observations are synthesised at (high-speed video; the images of
#: every frame are held in memory)
MAX_FPS = 1000.0
#: Pons-Moll et al.'s 10 sensors: sensor name → human31 bone (joint whose frame it rides on).
SENSOR_BONES: dict[str, str] = {
    "back": "pelvis",
    "l_forearm": "l_elbow",
    "r_forearm": "r_elbow",
    "l_shank": "l_knee",
    "r_shank": "r_knee",
    "chest": "spine",
    "l_upper_arm": "l_shoulder",
    "r_upper_arm": "r_shoulder",
    "l_thigh": "l_hip",
    "r_thigh": "r_hip",
}
#: The 5 tracking sensors (back, lower limbs); the other 5 are validation sensors.
TRACKING_SENSORS: tuple[str, ...] = ("back", "l_forearm", "r_forearm", "l_shank", "r_shank")


class ScenarioError(ValueError):
    """A scenario file or override is malformed (names the key and the expected value)."""


@dataclass
class SilhouetteConfig:
    """Foreground masks and their corruptions.

    Pixel sizes (``boundary_width``, ``hole_radius``, ``clutter_radius``) are given for a
    320-pixel-wide image and scale with the scenario's image width.

    Attributes:
        enabled: render silhouettes.
        boundary_flip: probability of flipping a pixel within ``boundary_width`` of the contour.
        boundary_width: half-width (px) of the band where boundary noise acts.
        holes: mean number (Poisson) of missing discs inside the foreground per view and frame.
        hole_radius: disc radius range ``[lo, hi]`` in px.
        clutter: mean number (Poisson) of false-positive elliptic blobs per view and frame.
        clutter_radius: blob semi-axis range ``[lo, hi]`` in px.
        shadow: add the body's floor shadow (projected along ``light_direction``) as foreground.
        drop_view: probability that a view is lost in a frame (mask all zero + flag).
    """

    enabled: bool = True
    boundary_flip: float = 0.0
    boundary_width: int = 1
    holes: float = 0.0
    hole_radius: list[float] = field(default_factory=lambda: [2.0, 5.0])
    clutter: float = 0.0
    clutter_radius: list[float] = field(default_factory=lambda: [4.0, 12.0])
    shadow: bool = False
    drop_view: float = 0.0


@dataclass
class ImageConfig:
    """Colour images for an appearance term.

    Attributes:
        enabled: render colour images.
        ambient: ambient light fraction; the rest is Lambertian from ``light_direction``.
        illumination_change: relative amplitude of the global brightness change over time.
        illumination_period_s: period (s) of that change (a sinusoid with a seeded phase).
        pixel_noise: std of additive Gaussian pixel noise (0–255 scale).
        shadow_darkening: fraction of light removed on the floor inside the body's shadow.
        smooth_shading: interpolate vertex normals (else flat per-face shading).
    """

    enabled: bool = True
    ambient: float = 0.35
    illumination_change: float = 0.0
    illumination_period_s: float = 4.0
    pixel_noise: float = 0.0
    shadow_darkening: float = 0.0
    smooth_shading: bool = True


@dataclass
class ImuConfig:
    """Inertial sensors: placement and error model (Pons-Moll et al. §4.2).

    Measured orientation of sensor ``s`` at frame ``t``::

        R_TS(t) = Rz(drift_s · t) · R_mis · R_TB(t + desync) · R_BS · N_s(t)

    Attributes:
        enabled: synthesise IMU orientations.
        sensors: sensor name → human31 bone (joint) it is strapped to.
        tracking: names of the tracking sensors (the others are validation sensors).
        offset: sensor-to-bone offsets ``R_BS``: ``random`` (uniform, seeded) or ``identity``.
        noise: device noise model: ``vmf`` (on S³, concentration ``kappa``), ``tangent``
            (isotropic tangent Gaussian, ``tangent_std_deg`` per axis), ``student_t`` (a
            multivariate Student t in the tangent space, scale ``tangent_std_deg``, ``dof``
            degrees of freedom: heavy-tailed bursts, and a model no tracker assumes) or ``none``.
        dof: degrees of freedom of ``student_t`` (> 0; smaller is heavier-tailed).
        heading_walk_deg: magnetic disturbance: each sensor's heading about world z follows a
            random walk with this std (degrees) per √s (0 = none).
        kappa: vMF concentration (1000 ≈ 5.6° median angle).
        tangent_std_deg: per-axis std (degrees) of the tangent Gaussian.
        misalignment_deg: angle between the inertial and tracking frames (a number, or a range
            ``[lo, hi]`` sampled uniformly), random axis, applied on the left, shared by all
            sensors.
        desync_frames: temporal offset of the IMU clock (fraction of a frame; slerp between
            neighbouring frames).
        drift_deg_per_min: heading drift rate about world z (each sensor drifts at this rate
            with a seeded random sign).
        drop_prob: probability that a sample is lost (the last valid value is held, ``valid``
            is False).
    """

    enabled: bool = True
    sensors: dict[str, str] = field(default_factory=lambda: dict(SENSOR_BONES))
    tracking: list[str] = field(default_factory=lambda: list(TRACKING_SENSORS))
    offset: str = "random"
    noise: str = "vmf"
    kappa: float = 1000.0
    tangent_std_deg: float = 3.6
    dof: float = 3.0
    heading_walk_deg: float = 0.0
    misalignment_deg: Any = 0.0
    desync_frames: float = 0.0
    drift_deg_per_min: float = 0.0
    drop_prob: float = 0.0


@dataclass
class DepthConfig:
    """One depth camera (Hauberg & Pedersen's stereo rig): a point cloud of the visible body.

    Attributes:
        enabled: synthesise depth points.
        position: camera centre (m), world.
        target: point looked at (m).
        image_size: depth image (width, height) in pixels.
        fov_deg: horizontal field of view.
        noise_std: std (m) of the depth error at 1 m, growing with depth squared (stereo).
        hole_prob: fraction of body pixels dropped at random.
        holes: mean number (Poisson) of missing discs per frame.
        hole_radius: disc radius range ``[lo, hi]`` in depth pixels.
        max_points: cap on points per frame (random subset, seeded); 0 = no cap.
    """

    enabled: bool = True
    position: list[float] = field(default_factory=lambda: [0.5, -3.0, 1.3])
    target: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.95])
    image_size: list[int] = field(default_factory=lambda: [160, 120])
    fov_deg: float = 55.0
    noise_std: float = 0.0
    hole_prob: float = 0.0
    holes: float = 0.0
    hole_radius: list[float] = field(default_factory=lambda: [2.0, 5.0])
    max_points: int = 0


@dataclass
class Joints2DConfig:
    """2D joint detections per camera.

    Attributes:
        enabled: synthesise detections.
        pixel_noise: std (px) of Gaussian noise on correct detections.
        outlier_prob: probability that a detection lands at a random image position.
        miss_prob: probability that a joint is not detected (confidence 0).
        confidence: range ``[lo, hi]`` of confidences of correct detections (uniform);
            outliers draw from ``[0.1, lo]``.
        occlusion: model self-occlusion: joints the body surface hides from a camera
            (:func:`~torchmocap.data.synthetic.occlusion.joint_occlusion`) are detected as below.
        occlusion_margin: metres of surface in front of a joint (beyond its own depth inside the
            body) that hide it.
        occluded_miss_prob: probability of missing a hidden joint.
        occluded_pixel_noise: std (px) of the noise on a hidden joint's detection.
        occluded_confidence: confidence range ``[lo, hi]`` of hidden joints' detections.
    """

    enabled: bool = True
    pixel_noise: float = 0.0
    outlier_prob: float = 0.0
    miss_prob: float = 0.0
    confidence: list[float] = field(default_factory=lambda: [1.0, 1.0])
    occlusion: bool = False
    occlusion_margin: float = 0.05
    occluded_miss_prob: float = 0.5
    occluded_pixel_noise: float = 3.0
    occluded_confidence: list[float] = field(default_factory=lambda: [0.1, 0.5])


@dataclass
class Scenario:
    """Everything the synthesiser needs besides the motion.

    Attributes:
        name: scenario name (file stem).
        rig: rig config name / path / inline mapping (see module docstring).
        image_size: (width, height) of every camera image.
        fps: frame rate clips are resampled to (at most :data:`MAX_FPS`).
        body: rendered surface: ``skinned`` (the bundled CC0 MakeHuman mesh, the default),
            ``capsules`` or ``anny`` (the Anny parametric body of ``phenotype``: the subject's
            motion retargeted onto that body's own skeleton, which becomes the ground truth's).
        phenotype: with ``body: anny``, the body's phenotype: a name of
            ``torchmocap/conf/phenotypes.yaml`` (``child``, ``heavy``, ``slim``, ``tall``, ...),
            a mapping ``{parameter: value in [0, 1]}`` (the others 0.5), ``random`` (drawn
            from ``phenotype_seed``) or null (Anny's default body).
        phenotype_seed: the seed of ``phenotype: random``.
        ground_truth: ``source`` (default): joint positions and bone orientations of the ground
            truth — and so the IMUs — are the exact motion-capture ones, while the images show
            the closest human31 pose (1–3° per bone apart, more where human31 cannot follow,
            e.g. forearm twist); ``fitted``: everything comes from the fitted human31 pose, so
            all modalities are mutually consistent (controlled experiments).
        recenter: translate the motion so its mean pelvis ground position is at the rig's
            ground centre ``center`` (ground truth moves with it).
        center: ``[x, y]`` ground point (m) the motion is centred on.
        light_direction: direction light travels (world, towards the floor) for shading and
            the floor shadow.
        silhouettes, images, imu, depth, joints2d: per-modality settings.
    """

    name: str = "custom"
    rig: Any = "ring4"
    image_size: list[int] = field(default_factory=lambda: [320, 240])
    fps: float = 25.0
    body: str = "skinned"
    phenotype: Any = None
    phenotype_seed: int = 0
    ground_truth: str = "source"
    recenter: bool = True
    center: list[float] = field(default_factory=lambda: [0.0, 0.0])
    light_direction: list[float] = field(default_factory=lambda: [0.4, 0.3, -1.0])
    silhouettes: SilhouetteConfig = field(default_factory=SilhouetteConfig)
    images: ImageConfig = field(default_factory=ImageConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    joints2d: Joints2DConfig = field(default_factory=Joints2DConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain-python copy (JSON/YAML serialisable)."""
        return dataclasses.asdict(self)

    def validate(self) -> Scenario:
        """Check ranges; raises :class:`ScenarioError` naming the key."""
        _check(self.body in ("skinned", "capsules", "anny"), "body",
               "'skinned', 'capsules' or 'anny'", self.body)
        if self.phenotype is not None or self.body == "anny":
            from torchmocap.body.phenotypes import resolve_phenotype

            _check(self.body == "anny", "phenotype", "null unless body is 'anny'",
                   self.phenotype)
            try:
                resolve_phenotype(self.phenotype, self.phenotype_seed, "scenario.phenotype")
            except ValueError as e:
                raise ScenarioError(str(e)) from e
        _check(self.ground_truth in ("source", "fitted"), "ground_truth", "'source' or 'fitted'",
               self.ground_truth)
        _check(len(self.image_size) == 2 and all(int(v) > 0 for v in self.image_size),
               "image_size", "[width, height] > 0", self.image_size)
        _check(0 < self.fps <= MAX_FPS, "fps", f"in (0, {MAX_FPS:g}]", self.fps)
        _check(len(self.light_direction) == 3 and self.light_direction[2] < 0,
               "light_direction", "3 values with a negative z (light travels down)",
               self.light_direction)
        s = self.silhouettes
        for k in ("boundary_flip", "drop_view"):
            _check(0 <= getattr(s, k) <= 1, f"silhouettes.{k}", "in [0, 1]", getattr(s, k))
        for k in ("holes", "clutter"):
            _check(getattr(s, k) >= 0, f"silhouettes.{k}", ">= 0", getattr(s, k))
        _check(s.boundary_width >= 1, "silhouettes.boundary_width", ">= 1", s.boundary_width)
        for k in ("hole_radius", "clutter_radius"):
            v = getattr(s, k)
            _check(len(v) == 2 and 0 < v[0] <= v[1], f"silhouettes.{k}", "[lo, hi] with "
                   "0 < lo <= hi", v)
        im = self.images
        _check(0 <= im.ambient <= 1, "images.ambient", "in [0, 1]", im.ambient)
        _check(0 <= im.illumination_change < 1, "images.illumination_change", "in [0, 1)",
               im.illumination_change)
        _check(im.illumination_period_s > 0, "images.illumination_period_s", "> 0",
               im.illumination_period_s)
        _check(im.pixel_noise >= 0, "images.pixel_noise", ">= 0", im.pixel_noise)
        _check(0 <= im.shadow_darkening <= 1, "images.shadow_darkening", "in [0, 1]",
               im.shadow_darkening)
        u = self.imu
        _check(u.noise in ("vmf", "tangent", "student_t", "none"), "imu.noise",
               "'vmf', 'tangent', 'student_t' or 'none'", u.noise)
        _check(_finite(u.dof) and u.dof > 0, "imu.dof", "a finite number > 0", u.dof)
        _check(_finite(u.heading_walk_deg) and u.heading_walk_deg >= 0, "imu.heading_walk_deg",
               "a finite number >= 0", u.heading_walk_deg)
        _check(u.offset in ("random", "identity"), "imu.offset", "'random' or 'identity'",
               u.offset)
        _check(u.kappa > 0, "imu.kappa", "> 0", u.kappa)
        _check(u.tangent_std_deg >= 0, "imu.tangent_std_deg", ">= 0", u.tangent_std_deg)
        _check(0 <= u.drop_prob < 1, "imu.drop_prob", "in [0, 1)", u.drop_prob)
        mis = u.misalignment_deg
        ok = isinstance(mis, (int, float)) and mis >= 0 or (
            isinstance(mis, (list, tuple)) and len(mis) == 2 and 0 <= mis[0] <= mis[1])
        _check(ok, "imu.misalignment_deg", "a number >= 0 or [lo, hi]", mis)
        _check(len(u.sensors) > 0, "imu.sensors", "at least one sensor", u.sensors)
        unknown = [t for t in u.tracking if t not in u.sensors]
        _check(not unknown, "imu.tracking", f"names among imu.sensors {list(u.sensors)}",
               unknown)
        d = self.depth
        _check(len(d.image_size) == 2 and all(int(v) > 0 for v in d.image_size),
               "depth.image_size", "[width, height] > 0", d.image_size)
        _check(d.noise_std >= 0, "depth.noise_std", ">= 0", d.noise_std)
        _check(0 <= d.hole_prob < 1, "depth.hole_prob", "in [0, 1)", d.hole_prob)
        _check(d.max_points >= 0, "depth.max_points", ">= 0", d.max_points)
        j = self.joints2d
        _check(j.pixel_noise >= 0, "joints2d.pixel_noise", ">= 0", j.pixel_noise)
        for k in ("outlier_prob", "miss_prob"):
            _check(0 <= getattr(j, k) <= 1, f"joints2d.{k}", "in [0, 1]", getattr(j, k))
        _check(len(j.confidence) == 2 and 0.1 <= j.confidence[0] <= j.confidence[1] <= 1,
               "joints2d.confidence", "[lo, hi] with 0.1 <= lo <= hi <= 1", j.confidence)
        _check(isinstance(j.occlusion, bool), "joints2d.occlusion", "true or false", j.occlusion)
        _check(_finite(j.occlusion_margin) and j.occlusion_margin >= 0,
               "joints2d.occlusion_margin", "a finite number >= 0 (metres)", j.occlusion_margin)
        _check(0 <= j.occluded_miss_prob <= 1, "joints2d.occluded_miss_prob", "in [0, 1]",
               j.occluded_miss_prob)
        _check(_finite(j.occluded_pixel_noise) and j.occluded_pixel_noise >= 0,
               "joints2d.occluded_pixel_noise", ">= 0", j.occluded_pixel_noise)
        oc = j.occluded_confidence
        _check(len(oc) == 2 and 0.01 <= oc[0] <= oc[1] <= 1, "joints2d.occluded_confidence",
               "[lo, hi] with 0.01 <= lo <= hi <= 1", oc)
        return self


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check(ok: bool, key: str, expected: str, got: Any) -> None:
    if not ok:
        raise ScenarioError(f"scenario.{key}: expected {expected}, got {got!r}")


def scenario_dir() -> Path:
    """Folder of the bundled scenario configs (``torchmocap/conf/scenario``)."""
    return Path(__file__).resolve().parents[2] / "conf" / "scenario"


def known_scenarios() -> list[str]:
    """Names of the bundled scenarios."""
    return sorted(p.stem for p in scenario_dir().glob("*.yaml"))


def _nest(overrides: dict[str, Any]) -> dict[str, Any]:
    """``{"imu.kappa": 3}`` → ``{"imu": {"kappa": 3}}`` (nested dicts pass through)."""
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        parts = str(key).split(".")
        d = out
        for p in parts[:-1]:
            d = d.setdefault(p, {})
            if not isinstance(d, dict):
                raise ScenarioError(f"overrides: {key!r} conflicts with another override")
        d[parts[-1]] = value
    return out


def _yaml_file(path: Path, key: str) -> Any:
    """The content of a YAML file (interpolations resolved), noted as an input; errors name
    ``key``, the file and the line."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from torchmocap.inputs import read_text_input, yaml_error_line

    text = read_text_input(path, ScenarioError, f"{key} file (YAML)")
    try:
        node = OmegaConf.create(text)
    except yaml.YAMLError as e:
        raise ScenarioError(f"{key}: {path}: not valid YAML ({yaml_error_line(e)})") from None
    except (OmegaConfBaseException, ValueError) as e:
        raise ScenarioError(f"{key}: cannot read {path}: {str(e).splitlines()[0]}") from None
    try:
        return OmegaConf.to_container(node, resolve=True)
    except OmegaConfBaseException as e:
        raise ScenarioError(f"{key}: {path}: {str(e).splitlines()[0]}") from None


def load_scenario(name_or_path: str | Path | Scenario | dict, _chain: tuple = (),
                  **overrides: Any) -> Scenario:
    """Load a scenario by bundled name (``clean``, ``studio``, ``outdoor``) or YAML path.

    Args:
        name_or_path: a bundled name, a path to a YAML file, a mapping, or a
            :class:`Scenario` (copied, then overridden).
        **overrides: values replacing the file's: nested mappings (``imu={"kappa": 300}``) or
            dotted keys (``**{"imu.kappa": 300}``).

    A YAML file may extend another scenario with ``base: <name or path>``: the base is loaded
    first and the file's own keys replace its values.

    Returns:
        a validated :class:`Scenario`.

    Raises:
        ScenarioError: unknown name / unreadable file, unknown keys, wrong types or ranges
            (the message names the key).

    Example:
        >>> load_scenario("studio", fps=30).fps
        30.0
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(name_or_path, Scenario):
        data: Any = name_or_path.to_dict()
        name = name_or_path.name
    elif isinstance(name_or_path, dict):
        data = dict(name_or_path)
        name = str(data.get("name", "custom"))
    else:
        s = str(name_or_path)
        path = Path(s)
        if not (s.endswith((".yaml", ".yml")) or path.is_file()):
            path = scenario_dir() / f"{s}.yaml"
            if not path.is_file():
                raise ScenarioError(f"scenario: unknown scenario {s!r}; expected one of "
                                    f"{known_scenarios()} or a path to a YAML file")
        if not path.is_file():
            raise ScenarioError(f"scenario: file not found: {path}")
        data = _yaml_file(path, "scenario")
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ScenarioError(f"scenario: {path} must hold a mapping at the top level")
        name = str(data.get("name", path.stem))
        if "base" in data:  # a scenario file may extend another: `base: monocular`
            base = data.pop("base")
            chain = (*_chain, str(path.resolve()))
            if not isinstance(base, str):
                raise ScenarioError(f"scenario.base: expected the name or path of another "
                                    f"scenario, got {base!r}")
            if len(chain) > 8 or str(path.resolve()) in _chain:
                raise ScenarioError(f"scenario.base: {path} extends itself (through {base!r})")
            data = OmegaConf.to_container(OmegaConf.merge(
                load_scenario(base, _chain=chain).to_dict(), data))
            data["name"] = name
    data.setdefault("name", name)
    try:
        cfg = OmegaConf.merge(OmegaConf.structured(Scenario), data, _nest(overrides))
        scenario = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as e:
        msg = str(e).splitlines()[0]
        key = getattr(e, "full_key", None)
        raise ScenarioError(f"scenario.{key}: {msg}" if key else f"scenario: {msg}") from e
    assert isinstance(scenario, Scenario)
    # OmegaConf returns containers for Any-typed fields: make them plain python
    if not isinstance(scenario.rig, (str, type(None))):
        scenario.rig = OmegaConf.to_container(OmegaConf.create(scenario.rig)) \
            if not isinstance(scenario.rig, (dict, list)) else scenario.rig
    if scenario.phenotype is not None and not isinstance(scenario.phenotype, (str, dict)):
        scenario.phenotype = OmegaConf.to_container(OmegaConf.create(scenario.phenotype)) \
            if hasattr(scenario.phenotype, "keys") else scenario.phenotype
    if isinstance(scenario.imu.misalignment_deg, (list, tuple)) or hasattr(
            scenario.imu.misalignment_deg, "__len__"):
        scenario.imu.misalignment_deg = [float(v) for v in scenario.imu.misalignment_deg]
    return scenario.validate()


# --------------------------------------------------------------------------- rigs


def _rig_search_dirs() -> list[Path]:
    here = Path(__file__).resolve()
    return [here.parents[2] / "conf" / "rig", here.parents[3] / "conf" / "rig"]


def _rig_from_config(cfg: dict[str, Any], image_size: list[int] | None, where: str):
    from torchmocap.cameras import CameraRig, rig_from_dict

    cfg = dict(cfg)
    if "_target_" in cfg:
        import hydra.utils

        if image_size is not None and "image_size" in cfg:
            cfg["image_size"] = list(image_size)
        try:
            rig = hydra.utils.instantiate(cfg)
        except Exception as e:  # noqa: BLE001 - re-raised with the config named
            raise ScenarioError(f"{where}: cannot instantiate rig config: {e}") from e
        if not isinstance(rig, CameraRig):
            raise ScenarioError(f"{where}: _target_ must build a CameraRig, got "
                                f"{type(rig).__name__}")
        return rig
    return rig_from_dict(cfg, source=where)


def build_rig(rig: Any, image_size: list[int] | tuple[int, int] | None = None):
    """Resolve a scenario's ``rig`` entry to a :class:`~torchmocap.cameras.CameraRig`.

    Args:
        rig: rig config name (``ring4``, ``ceiling4``), path (factory YAML or calibration file),
            inline mapping, or a ``CameraRig`` (returned as is, resized if needed).
        image_size: ``(width, height)`` every camera must have; intrinsics are scaled when the
            rig's images have the same aspect ratio.

    Raises:
        ScenarioError: unknown name, unreadable file, or an incompatible aspect ratio.
    """

    from torchmocap.cameras import CameraRig, read_rig

    if isinstance(rig, CameraRig):
        out = rig
    elif isinstance(rig, dict):
        out = _rig_from_config(rig, image_size, "scenario.rig")
    elif isinstance(rig, (str, Path)):
        s = str(rig)
        path = Path(s)
        if not path.is_file():
            found = [d / f"{s}.yaml" for d in _rig_search_dirs() if (d / f"{s}.yaml").is_file()]
            if not found:
                names = sorted({p.stem for d in _rig_search_dirs() if d.is_dir()
                                for p in d.glob("*.yaml")})
                raise ScenarioError(f"scenario.rig: unknown rig {s!r}; expected a rig config "
                                    f"name {names}, a file path or an inline mapping")
            path = found[0]
        if path.suffix.lower() in (".yaml", ".yml"):
            data = _yaml_file(path, "scenario.rig")
            if isinstance(data, dict) and "_target_" in data:
                out = _rig_from_config(data, image_size, f"scenario.rig ({path})")
            else:
                out = read_rig(path)
        else:
            out = read_rig(path)
    else:
        raise ScenarioError(f"scenario.rig: expected a name, path or mapping, got "
                            f"{type(rig).__name__}")
    if image_size is None:
        return out
    w, h = int(image_size[0]), int(image_size[1])
    size = out.image_size
    if bool((size[:, 0] == w).all() and (size[:, 1] == h).all()):
        return out
    cams = []
    for c in range(out.num_cameras):
        cw, ch = int(size[c, 0]), int(size[c, 1])
        if abs(cw * h - ch * w) > max(w, h) * 1e-6 * cw:
            raise ScenarioError(f"scenario.image_size: {w}x{h} has another aspect ratio than "
                                f"camera {out.names[c]} ({cw}x{ch})")
        cams.append(out.subset([c]).scaled_images(w / cw))
    K = torch.cat([c.K for c in cams])
    R = torch.cat([c.R for c in cams])
    t = torch.cat([c.t for c in cams])
    dist = torch.cat([c.dist for c in cams])
    return CameraRig(K, R, t, (w, h), dist, out.names)
