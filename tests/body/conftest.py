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
