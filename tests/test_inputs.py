"""torchmocap.inputs: the readers note what they read, digests follow content (not times),
folder listings count, and text inputs fail with the file named."""

from __future__ import annotations

import os
import shutil

import pytest

from torchmocap.inputs import (
    changed_inputs,
    file_digest,
    input_log,
    note_input,
    read_text_input,
    yaml_error_line,
)


def test_feature_amc_notes_the_asf_found_beside_it(tmp_path, shared_data):
    """An AMC's skeleton is found in its folder: the ASF and the folder's listing are inputs
    (neither is named by any setting)."""
    from torchmocap.io import load_motion

    for f in ("01.asf", "01_01.amc"):
        shutil.copy(shared_data / "mocap" / "cmu" / f, tmp_path / f)
    with input_log() as log:
        load_motion(tmp_path / "01_01.amc", skip_frames=0)
    assert set(log.paths) >= {str(tmp_path / "01.asf"), str(tmp_path / "01_01.amc"),
                              str(tmp_path)}


def test_feature_scenario_base_chain_is_noted(tmp_path):
    from torchmocap.data.synthetic import load_scenario

    (tmp_path / "base.yaml").write_text("base: studio\nfps: 20\n")
    (tmp_path / "child.yaml").write_text(f"base: {tmp_path / 'base.yaml'}\nimage_size: [80, 60]\n")
    with input_log() as log:
        sc = load_scenario(str(tmp_path / "child.yaml"))
    assert sc.fps == 20 and list(sc.image_size) == [80, 60]
    assert {str(tmp_path / "base.yaml"), str(tmp_path / "child.yaml")} <= set(log.paths)


def test_feature_digests_follow_content(tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("one")
    with input_log() as log:
        note_input(f)
        note_input(tmp_path)
        note_input(tmp_path / "missing.txt")
    rec = log.digests()
    assert rec[str(tmp_path / "missing.txt")] == "-" and changed_inputs(rec) == []
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # touched, same content
    assert changed_inputs(rec) == []
    f.write_text("two")  # same size, other content
    assert changed_inputs(rec) == [str(f)]
    f.write_text("one")
    (tmp_path / "b.txt").write_text("new")  # the folder's listing changed
    assert changed_inputs(rec) == [str(tmp_path)]
    (tmp_path / "b.txt").unlink()
    (tmp_path / "missing.txt").write_text("appeared")
    assert changed_inputs(rec) == [str(tmp_path), str(tmp_path / "missing.txt")]


def test_cardinality_logs_nest_and_note_nothing_when_closed(tmp_path):
    note_input(tmp_path / "x")  # no log open: nothing to record, no error
    with input_log() as outer:
        note_input(tmp_path / "a")
        with input_log() as inner:
            note_input(tmp_path / "b")
    assert outer.paths == [str(tmp_path / "a"), str(tmp_path / "b")]
    assert inner.paths == [str(tmp_path / "b")]


def test_exception_binary_text_input_names_the_file(tmp_path):
    p = tmp_path / "Camera1.cal"
    p.write_bytes(b"\x00\xcb\xff\x10 binary")
    with pytest.raises(KeyError, match=r"Camera1\.cal: not a text file \(byte 0xcb at offset 1"):
        read_text_input(p, KeyError, "calibration")
    with pytest.raises(ValueError, match="cannot read"):
        read_text_input(tmp_path / "nothing.yaml")


def test_feature_text_input_drops_a_byte_order_mark(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_bytes("\ufeffkey: 1\n".encode())
    with input_log() as log:
        assert read_text_input(p) == "key: 1\n"
    assert log.paths == [str(p)] and file_digest(p) != "-"


def test_feature_yaml_error_on_one_line():
    import yaml

    with pytest.raises(yaml.YAMLError) as e:
        yaml.safe_load("name: x\nsize: [320, 240\nfps: 25\n")
    line = yaml_error_line(e.value)
    assert line.startswith("line 3, column 4: ") and "\n" not in line
