"""The documentation site builds without a warning (``mkdocs build --strict``): every page of the
nav exists, every link between pages resolves, and the API reference renders every public
docstring of the package."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_docs_build_strict(tmp_path):
    exe = Path(sys.executable).parent / "mkdocs"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    r = subprocess.run([str(exe), "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d",
                        str(tmp_path / "site")], capture_output=True, text=True, timeout=600,
                       cwd=ROOT, env=env)
    assert r.returncode == 0, r.stderr[-4000:]
    assert "WARNING" not in r.stderr, r.stderr[-4000:]
    assert (tmp_path / "site" / "api" / "filters" / "index.html").is_file()
    page = (tmp_path / "site" / "api" / "evaluation" / "index.html").read_text()
    assert "evaluate_track" in page and "leave_one_camera_out" in page


def _text_files():
    r = subprocess.run(["git", "ls-files", "*.md", "*.py", "*.yaml", "*.toml", "*.cfg", "*.txt"],
                       capture_output=True, text=True, cwd=ROOT)
    if r.returncode != 0:
        pytest.skip("not a git checkout")
    return [ROOT / p for p in r.stdout.split()]


def test_no_merge_conflict_markers():
    bad = []
    for path in _text_files():
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if line.startswith(("<<<<<<< ", ">>>>>>> ")) or line == "=======":
                bad.append(f"{path.relative_to(ROOT)}:{n}")
    assert not bad, bad


def test_readme_links_resolve():
    import re

    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(([^)#\s]+)", text)
    missing = [t for t in targets if not t.startswith("http") and not (ROOT / t).exists()]
    assert targets and not missing, missing
