"""Shared helpers of the experiment-script tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def load_script():
    """``load_script("hauberg2011/report.py")`` imports a script of ``experiments/`` by path
    (the scripts are not a package) and returns the module."""

    def load(rel: str):
        path = ROOT / "experiments" / rel
        spec = importlib.util.spec_from_file_location(path.stem + "_" + path.parent.name, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # dataclasses look their module up by name
        spec.loader.exec_module(mod)
        return mod

    return load
