"""TRC (track row column) marker files, as Pose2Sim and OpenSim write them.

Layout (tab-separated)::

    PathFileType  4  (X/Y/Z)  <name>
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  ...
    60  60  10  21  m  60  ...
    Frame#  Time  RHip  <tab>  <tab>  RKnee ...
            X1  Y1  Z1  X2  Y2  Z2 ...
    (an optional blank line)
    1  0.0166  x  y  z  x  y  z ...

one row per frame: its number, its time (s) and ``3 M`` coordinates (an empty field is a
missing marker: NaN). Coordinates are converted to metres from the file's ``Units`` (m, cm,
mm). The files are Y-up (OpenSim): Pose2Sim writes its Z-up calibration world as
``(x, y, z)_trc = (y, z, x)_world``; :func:`trc_to_z_up` (:meth:`TrcData.z_up`) turns them
back into torchmocap's world.

Example:
    >>> data = read_trc("markers.trc")  # doctest: +SKIP
    >>> data.points.shape, data.z_up().shape  # doctest: +SKIP
    (torch.Size([10, 21, 3]), torch.Size([10, 21, 3]))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from torchmocap.io.errors import MotionFormatError

__all__ = ["TRC_Y_UP_TO_Z_UP", "TrcData", "read_trc", "trc_to_z_up"]

#: ``p_world = TRC_Y_UP_TO_Z_UP @ p_trc``: ``(x, y, z)_trc = (y, z, x)_world`` (a proper rotation).
TRC_Y_UP_TO_Z_UP = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                                dtype=torch.float64)
_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def trc_to_z_up(points: torch.Tensor) -> torch.Tensor:
    """Y-up TRC points ``(*, 3)`` in torchmocap's Z-up world: ``(x, y, z) -> (z, x, y)``."""
    if not isinstance(points, torch.Tensor) or points.shape[-1:] != (3,):
        shape = tuple(points.shape) if isinstance(points, torch.Tensor) else type(points).__name__
        raise ValueError(f"points: expected shape (*, 3), got {shape}")
    return points[..., [2, 0, 1]]


@dataclass
class TrcData:
    """The contents of a TRC file.

    Attributes:
        marker_names: the ``M`` marker names.
        frames: ``(T,)`` int64 frame numbers.
        times: ``(T,)`` float64 times (s).
        points: ``(T, M, 3)`` float64 positions in metres, in the file's (Y-up) axes; NaN where
            a marker is missing.
        rate: the data rate (frames per second).
        units: the file's length unit (``m``, ``cm`` or ``mm``).
        path: the file read.
    """

    marker_names: list[str]
    frames: torch.Tensor
    times: torch.Tensor
    points: torch.Tensor
    rate: float
    units: str
    path: str

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    def z_up(self) -> torch.Tensor:
        """``(T, M, 3)`` positions in torchmocap's Z-up world (:func:`trc_to_z_up`)."""
        return trc_to_z_up(self.points)

    def marker_index(self, name: str) -> int:
        """Column of marker ``name`` in ``points``."""
        try:
            return self.marker_names.index(name)
        except ValueError:
            raise KeyError(f"unknown marker {name!r}; markers: {self.marker_names}") from None


def _number(tok: str, what: str, path: str, line: int) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise MotionFormatError(f"{what}: expected a number, got {tok!r}", path, line) from None
    if not math.isfinite(v):
        raise MotionFormatError(f"{what} is not finite ({tok})", path, line)
    return v


def read_trc(path: str | Path) -> TrcData:
    """Read a TRC marker file (module docstring).

    Raises:
        MotionFormatError: a malformed file (names the file and line): a missing header line,
            a header whose marker count or frame count does not match the data, an unknown
            unit, a row with the wrong number of fields or a non-numeric value.
        FileNotFoundError: no file at ``path``.
    """
    from torchmocap.inputs import note_input

    p = str(path)
    note_input(path)
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such TRC file") from None
    lines = text.splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise MotionFormatError("not a TRC file (expected 'PathFileType' on line 1 and a "
                                "5-line header)", p, 1)
    keys = lines[1].split("\t")
    vals = lines[2].split("\t")
    if len(vals) < len(keys):
        raise MotionFormatError(f"{len(keys)} header names but {len(vals)} values", p, 3)
    header = {k.strip(): v.strip() for k, v in zip(keys, vals)}
    for k in ("DataRate", "NumFrames", "NumMarkers", "Units"):
        if k not in header:
            raise MotionFormatError(f"header has no {k!r} (names: {list(header)})", p, 2)
    rate = _number(header["DataRate"], "DataRate", p, 3)
    if rate <= 0:
        raise MotionFormatError(f"DataRate must be > 0, got {rate}", p, 3)
    n_frames = int(_number(header["NumFrames"], "NumFrames", p, 3))
    n_markers = int(_number(header["NumMarkers"], "NumMarkers", p, 3))
    units = header["Units"].lower()
    if units not in _UNITS:
        raise MotionFormatError(f"unknown Units {header['Units']!r} (expected one of "
                                f"{list(_UNITS)})", p, 3)
    cols = lines[3].split("\t")
    if len(cols) < 2 or cols[0].strip() != "Frame#":
        raise MotionFormatError("expected 'Frame#' and 'Time' before the marker names", p, 4)
    names = [c.strip() for c in cols[2:] if c.strip()]
    if len(names) != n_markers:
        raise MotionFormatError(f"NumMarkers is {n_markers} but {len(names)} marker names "
                                "are listed", p, 4)
    width = 2 + 3 * n_markers
    frames, times, rows = [], [], []
    for i, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        f = line.rstrip("\r\n").split("\t")
        if len(f) > width and not any(x.strip() for x in f[width:]):
            f = f[:width]
        if len(f) != width:
            raise MotionFormatError(f"a row has {len(f)} fields, expected {width} (frame, time "
                                    f"and 3 x {n_markers} coordinates)", p, i)
        frames.append(int(_number(f[0], "frame number", p, i)))
        times.append(_number(f[1], "time", p, i))
        rows.append([_number(x, "coordinate", p, i) if x.strip() else math.nan
                     for x in f[2:]])
    if len(rows) != n_frames:
        raise MotionFormatError(f"NumFrames is {n_frames} but the file has {len(rows)} data "
                                "rows", p, 3)
    pts = torch.tensor(rows, dtype=torch.float64).reshape(len(rows), n_markers, 3)
    return TrcData(marker_names=names, frames=torch.tensor(frames, dtype=torch.long),
                   times=torch.tensor(times, dtype=torch.float64), points=pts * _UNITS[units],
                   rate=rate, units=units, path=p)
