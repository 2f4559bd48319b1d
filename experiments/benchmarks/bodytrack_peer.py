"""PARSEC bodytrack, the C++ peer of the real-frame anneal: built from its sources into a
temporary folder at benchmark time and timed on the same frame as ours.

PARSEC's ``bodytrack`` (Deutscher & Reid's annealed particle filter, 10 truncated cones, edge +
foreground likelihood) prints no timings, so a run is timed from the outside: the whole
process (start, calibration and image loading, edge maps, the initial weighting of the
particles, the annealing layers, writing ``poses.txt``), wall and CPU (user + system, from the
children's resource usage). Its annealing alone is estimated from two runs that differ only in
the number of layers: ``(t(P, K) - t(P, 1)) * K / (K - 1)`` — the cost of ``K`` layers of ``P``
particles, the fixed part (start, loading, edge maps) cancelled.

Used by ``tracker.py``; run alone to time the peer:

    python experiments/benchmarks/bodytrack_peer.py [--peer DIR] [--frame DIR] [--repeats 5]

The sources default to ``../shared/peers/parsec_bodytrack`` and the frame to
``../shared/data/multiview/bodytrack_sequenceB_1``, both relative to the repository root.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import statistics
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULT_PEER = REPO.parent / "shared" / "peers" / "parsec_bodytrack"
DEFAULT_FRAME = REPO.parent / "shared" / "data" / "multiview" / "bodytrack_sequenceB_1"
CAMERAS = 4
#: the peer's thread models (its command line): serial code, or OpenMP with N threads
SERIAL, OPENMP = 4, 3


class PeerUnavailable(RuntimeError):
    """The peer cannot be built or run here (the benchmark skips its rows, saying why)."""


class PeerOutputError(RuntimeError):
    """The peer ran but did not do what was asked (its exit status is 0 even then)."""


def find_compiler() -> str | None:
    """The C++ compiler the build script calls (``g++`` on ``PATH``), or None."""
    return shutil.which("g++")


def skip_reason(peer_dir: Path, frame_dir: Path, compiler: str | None) -> str | None:
    """Why the peer's rows cannot be measured here, or None when they can."""
    if compiler is None:
        return "no C++ compiler (g++) on PATH to build PARSEC bodytrack"
    if not (Path(peer_dir) / "build.sh").is_file():
        return (f"no PARSEC bodytrack sources at {peer_dir} (build.sh missing; "
                "pass --peer DIR)")
    missing = [p for p in ("CALIB", "CAM1", "FG1") if not (Path(frame_dir) / p).is_dir()]
    if missing:
        return f"no bodytrack frame at {frame_dir} ({', '.join(missing)} missing; pass --frame DIR)"
    return None


def build(peer_dir: Path, out_dir: Path, timeout: float = 600) -> Path:
    """Build the peer with its ``build.sh`` into ``out_dir``; the path of the binary.

    Raises:
        PeerUnavailable: the build failed or timed out (the compiler's last lines quoted).
    """
    out_dir = Path(out_dir)
    try:
        res = subprocess.run(["bash", str(Path(peer_dir) / "build.sh"), str(out_dir)],
                             capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise PeerUnavailable(f"building PARSEC bodytrack took over {timeout:.0f} s") from None
    binary = out_dir / "bodytrack"
    if res.returncode != 0 or not binary.is_file():
        tail = (res.stderr or res.stdout).strip().splitlines()[-5:]
        raise PeerUnavailable("building PARSEC bodytrack failed (exit status "
                              f"{res.returncode}): " + " | ".join(tail))
    return binary


def writable_frame(frame_dir: Path, tmp: Path) -> Path:
    """A copy of the frame folder under ``tmp``: the peer writes ``poses.txt`` into it."""
    dst = Path(tmp) / "frame"
    shutil.copytree(frame_dir, dst, dirs_exist_ok=True)
    for p in dst.rglob("*"):
        p.chmod(p.stat().st_mode | 0o200)
    dst.chmod(dst.stat().st_mode | 0o200)
    return dst


def command(binary: Path, frame: Path, particles: int, layers: int, threads: int) -> list[str]:
    """The peer's command line for one frame: serial code for one thread, OpenMP otherwise
    (the dataset path needs its trailing slash; no BMP output)."""
    for name, v in (("particles", particles), ("layers", layers), ("threads", threads)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
    model = SERIAL if threads == 1 else OPENMP
    return [str(binary), str(frame).rstrip("/") + "/", str(CAMERAS), "1", str(particles),
            str(layers), str(model), str(threads), "0"]


@dataclass(frozen=True)
class PeerOutput:
    """What the peer's standard output says it did."""

    threading: str  # "serial" or "openmp"
    threads: int
    particles: int
    layers: int
    frames: int


def parse_output(text: str) -> PeerOutput:
    """The run described by the peer's standard output.

    Raises:
        PeerOutputError: an error message of the peer (it exits with status 0 on errors), a
            thread model it was not built with, or the expected lines missing.
    """
    for bad in ("Error", "Not compiled with", "Internal error", "Invalid"):
        line = next((ln for ln in text.splitlines() if bad in ln), None)
        if line is not None:
            raise PeerOutputError(f"PARSEC bodytrack reported: {line.strip()}")
    if "Running Single Threaded" in text:
        threading, threads = "serial", 1
    else:
        m = re.search(r"Threading with OpenMP\s+Number of Threads : (\d+)", text)
        if m is None:
            raise PeerOutputError("PARSEC bodytrack's output names no thread model "
                                  "(expected 'Running Single Threaded' or 'Threading with "
                                  "OpenMP')")
        threading, threads = "openmp", int(m.group(1))
    m = re.search(r"(\d+) particles with (\d+) annealing layers", text)
    if m is None:
        raise PeerOutputError("PARSEC bodytrack's output has no 'N particles with K annealing "
                              "layers' line")
    frames = len(re.findall(r"^Processing frame \d+", text, flags=re.M))
    return PeerOutput(threading, threads, int(m.group(1)), int(m.group(2)), frames)


def check_output(out: PeerOutput, particles: int, layers: int, threads: int) -> None:
    """Raise :class:`PeerOutputError` unless ``out`` is the one-frame run that was asked for."""
    want = PeerOutput("serial" if threads == 1 else "openmp", threads, particles, layers, 1)
    if out != want:
        raise PeerOutputError(f"PARSEC bodytrack ran {out}, expected {want}")


def read_pose(path: Path) -> list[float]:
    """The estimate the peer wrote (one line of numbers per frame; the last line).

    Raises:
        PeerOutputError: no file, an empty file or non-numeric values.
    """
    try:
        lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip()]
    except OSError as e:
        raise PeerOutputError(f"PARSEC bodytrack wrote no pose file {path}: {e}") from None
    if not lines:
        raise PeerOutputError(f"PARSEC bodytrack's pose file {path} is empty")
    try:
        return [float(v) for v in lines[-1].split()]
    except ValueError:
        raise PeerOutputError(f"PARSEC bodytrack's pose file {path}: expected numbers, got "
                              f"{lines[-1][:80]!r}") from None


@dataclass(frozen=True)
class PeerRun:
    """One timed run: whole-process wall and CPU seconds, and the pose it wrote."""

    wall: float
    cpu: float
    pose: list[float]


def run(binary: Path, frame: Path, particles: int, layers: int, threads: int,
        timeout: float = 600) -> PeerRun:
    """Run the peer once on ``frame`` (a writable copy) and time the whole process."""
    poses = Path(frame) / "poses.txt"
    poses.unlink(missing_ok=True)
    argv = command(binary, frame, particles, layers, threads)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        res = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        raise PeerOutputError(f"PARSEC bodytrack ran over {timeout:.0f} s: "
                              f"{' '.join(argv)}") from None
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise PeerOutputError(f"PARSEC bodytrack exited with status {res.returncode}: "
                              f"{res.stderr.strip()[-300:]}")
    check_output(parse_output(res.stdout), particles, layers, threads)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return PeerRun(wall, cpu, read_pose(poses))


def anneal_only(t_layers: float, t_one: float, layers: int) -> float:
    """Estimated time of ``layers`` annealing layers from whole-process times with ``layers``
    and with one layer: ``(t_layers - t_one) * layers / (layers - 1)``."""
    if isinstance(layers, bool) or not isinstance(layers, int) or layers < 2:
        raise ValueError(f"layers: expected an int >= 2, got {layers!r}")
    return (t_layers - t_one) * layers / (layers - 1)


class Peer:
    """The peer built into a temporary folder, with a writable copy of the frame; use as a
    context manager (the folder is removed on exit)."""

    def __init__(self, peer_dir: Path = DEFAULT_PEER, frame_dir: Path = DEFAULT_FRAME):
        reason = skip_reason(peer_dir, frame_dir, find_compiler())
        if reason is not None:
            raise PeerUnavailable(reason)
        self.peer_dir, self.frame_dir = Path(peer_dir), Path(frame_dir)

    def __enter__(self) -> Peer:
        self._tmp = tempfile.TemporaryDirectory(prefix="bodytrack_peer_")
        tmp = Path(self._tmp.name)
        t0 = time.perf_counter()
        self.binary = build(self.peer_dir, tmp / "build")
        self.build_seconds = time.perf_counter() - t0
        self.frame = writable_frame(self.frame_dir, tmp)
        return self

    def __exit__(self, *exc) -> None:
        self._tmp.cleanup()

    def run(self, particles: int, layers: int, threads: int) -> PeerRun:
        return run(self.binary, self.frame, particles, layers, threads)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", type=Path, default=DEFAULT_PEER, help="PARSEC bodytrack sources")
    ap.add_argument("--frame", type=Path, default=DEFAULT_FRAME, help="bodytrack frame folder")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    try:
        peer = Peer(args.peer, args.frame)
    except PeerUnavailable as e:
        print(f"PARSEC bodytrack skipped: {e}")
        return
    with peer:
        print(f"# built in {peer.build_seconds:.1f} s; load average {os.getloadavg()[0]:.2f}")
        print("| particles x layers | threads | whole process wall s | CPU s | "
              "annealing alone (est.) wall s |")
        print("|---|---|---|---|---|")
        for particles, layers in ((200, 15), (4000, 5)):
            for threads in (1, 2):
                full, one = [], []
                for _ in range(args.repeats):
                    full.append(peer.run(particles, layers, threads))
                    one.append(peer.run(particles, 1, threads))
                wall = statistics.median(r.wall for r in full)
                est = anneal_only(wall, statistics.median(r.wall for r in one), layers)
                print(f"| {particles} x {layers} | {threads} | {wall:.3f} | "
                      f"{statistics.median(r.cpu for r in full):.3f} | {est:.3f} |")


if __name__ == "__main__":
    main()
