"""Fuzz the readers with mutated real files: they load or raise MotionFormatError, nothing else."""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchmocap.io import MotionFormatError, read_amc, read_bvh
from torchmocap.io.asf import parse_asf
from torchmocap.io.bvh import parse_bvh

BAD_TOKENS = ["nan", "inf", "-inf", "1e999", "", "x", "-", "{", "}", "JOINT", "End", "Site",
              "CHANNELS", "OFFSET", "MOTION", "Frames:", "0", "-1", "3", "7", "1e-320",
              "Xrotation", "Qrotation", "root", "begin", "end", ":bonedata", "dof", "rx", "\u00e9"]
SETTINGS = settings(max_examples=100, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@st.composite
def mutate(draw, text: str) -> str:
    lines = text.splitlines(keepends=True)
    for _ in range(draw(st.integers(1, 3))):
        if not lines:
            break
        op = draw(st.sampled_from(["truncate", "delete", "duplicate", "corrupt", "swap",
                                   "insert"]))
        i = draw(st.integers(0, len(lines) - 1))
        if op == "truncate":
            joined = "".join(lines)
            cut = draw(st.integers(0, len(joined)))
            lines = joined[:cut].splitlines(keepends=True)
        elif op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "insert":
            lines.insert(i, " ".join(draw(st.lists(st.sampled_from(BAD_TOKENS), max_size=4)))
                         + "\n")
        else:
            toks = lines[i].split()
            if toks:
                k = draw(st.integers(0, len(toks) - 1))
                toks[k] = draw(st.sampled_from(BAD_TOKENS) | st.text(max_size=4))
                lines[i] = " ".join(toks) + "\n"
    return "".join(lines)


@pytest.fixture(scope="module")
def small_bvh(cmu) -> str:
    text = (cmu / "131_01.bvh").read_text()
    head, motion = text.split("MOTION", 1)
    frames = motion.strip().splitlines()[2:8]
    motion = f"MOTION\nFrames: {len(frames)}\nFrame Time: .0083333\n"
    return head + motion + "\n".join(frames) + "\n"


@pytest.fixture(scope="module")
def small_amc(cmu) -> tuple[str, str]:
    amc = (cmu / "01_01.amc").read_text(encoding="latin-1").splitlines(keepends=True)
    end = amc.index("4\n")  # first three frames
    return (cmu / "01.asf").read_text(encoding="latin-1"), "".join(amc[:end])


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _loads_or_format_error(read) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            clip = read()
        except MotionFormatError:
            return
    assert torch.isfinite(clip.global_positions()).all()  # a clip that loads also moves


def test_baselines_load(small_bvh, small_amc, workdir):
    (workdir / "ok.bvh").write_text(small_bvh)
    assert read_bvh(workdir / "ok.bvh").num_frames == 6
    (workdir / "ok.asf").write_text(small_amc[0])
    (workdir / "ok.amc").write_text(small_amc[1])
    assert read_amc(workdir / "ok.amc", workdir / "ok.asf").num_frames == 3


@SETTINGS
@given(data=st.data())
def test_fuzz_bvh(small_bvh, workdir, data):
    path = workdir / "fuzz.bvh"
    path.write_text(data.draw(mutate(small_bvh)), encoding="utf-8")
    _loads_or_format_error(lambda: read_bvh(path))


@SETTINGS
@given(data=st.data())
def test_fuzz_amc(small_amc, workdir, data):
    (workdir / "f.asf").write_text(small_amc[0], encoding="latin-1")
    amc = workdir / "f.amc"
    amc.write_text(data.draw(mutate(small_amc[1])), encoding="utf-8")
    _loads_or_format_error(lambda: read_amc(amc, workdir / "f.asf"))


@SETTINGS
@given(data=st.data())
def test_fuzz_asf(small_amc, workdir, data):
    asf = workdir / "g.asf"
    asf.write_text(data.draw(mutate(small_amc[0])), encoding="utf-8")
    (workdir / "g.amc").write_text(small_amc[1], encoding="latin-1")
    _loads_or_format_error(lambda: read_amc(workdir / "g.amc", asf))


@SETTINGS
@given(text=st.text(max_size=200))
def test_fuzz_garbage(text):
    for parse in (lambda: parse_asf(text, "x.asf"), lambda: parse_bvh(text, "x.bvh")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                parse()
            except MotionFormatError:
                pass
