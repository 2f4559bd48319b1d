"""experiments/benchmarks/bodytrack_peer.py: the pure parts of the PARSEC peer's harness (its
command line, the parsing of its output and pose file, the skip logic, the annealing-only
estimate). Nothing is built or timed here."""

from __future__ import annotations

import pytest

SERIAL_OUT = """PARSEC Benchmark Suite

Running Single Threaded

Using dataset : frame/
200 particles with 15 annealing layers

Processing frame 0
"""

OPENMP_OUT = """PARSEC Benchmark Suite
Threading with OpenMP
Number of Threads : 2
Using dataset : frame/
4000 particles with 5 annealing layers

Processing frame 0
"""


@pytest.fixture(scope="module")
def peer(load_script):
    return load_script("benchmarks/bodytrack_peer.py")


def test_command_serial_for_one_thread_openmp_otherwise(peer, tmp_path):
    one = peer.command(tmp_path / "bodytrack", tmp_path / "frame", 200, 15, 1)
    assert one[1:] == [f"{tmp_path / 'frame'}/", "4", "1", "200", "15", "4", "1", "0"]
    two = peer.command(tmp_path / "bodytrack", f"{tmp_path / 'frame'}/", 4000, 5, 2)
    assert two[1:] == [f"{tmp_path / 'frame'}/", "4", "1", "4000", "5", "3", "2", "0"]
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="layers"):
            peer.command(tmp_path / "b", tmp_path, 200, bad, 1)


def test_parse_output_reads_the_thread_model_and_the_run(peer):
    assert peer.parse_output(SERIAL_OUT) == peer.PeerOutput("serial", 1, 200, 15, 1)
    assert peer.parse_output(OPENMP_OUT) == peer.PeerOutput("openmp", 2, 4000, 5, 1)
    two = OPENMP_OUT + "Processing frame 1\n"
    assert peer.parse_output(two).frames == 2


@pytest.mark.parametrize("text, match", [
    (SERIAL_OUT.replace("Processing frame 0", "Update Error : Model observation failed"),
     "Model observation failed"),
    ("PARSEC Benchmark Suite\nNot compiled with Intel TBB support. \n", "Not compiled"),
    ("PARSEC Benchmark Suite\n\nError loading initialization data.\n", "initialization"),
    ("PARSEC Benchmark Suite\n", "no thread model"),
    (SERIAL_OUT.replace("200 particles with 15 annealing layers", ""), "annealing layers"),
])
def test_parse_output_rejects_failed_runs(peer, text, match):
    # the peer exits with status 0 on every one of these
    with pytest.raises(peer.PeerOutputError, match=match):
        peer.parse_output(text)


def test_check_output_wants_exactly_the_run_asked_for(peer):
    out = peer.parse_output(SERIAL_OUT)
    peer.check_output(out, 200, 15, 1)
    for args in ((200, 15, 2), (4000, 15, 1), (200, 5, 1)):
        with pytest.raises(peer.PeerOutputError, match="expected"):
            peer.check_output(out, *args)
    with pytest.raises(peer.PeerOutputError, match="frames=0"):
        peer.check_output(peer.parse_output(SERIAL_OUT.replace("Processing frame 0", "")),
                          200, 15, 1)


def test_read_pose_last_line_of_numbers(peer, tmp_path):
    p = tmp_path / "poses.txt"
    p.write_text("1 2 3 \n0.0922899 0.0132553 -0.107401 133.381 \n")
    assert peer.read_pose(p) == [0.0922899, 0.0132553, -0.107401, 133.381]
    with pytest.raises(peer.PeerOutputError, match="no pose file"):
        peer.read_pose(tmp_path / "missing.txt")
    p.write_text("\n")
    with pytest.raises(peer.PeerOutputError, match="empty"):
        peer.read_pose(p)
    p.write_text("1 2 nan? x\n")
    with pytest.raises(peer.PeerOutputError, match="expected numbers"):
        peer.read_pose(p)


def test_skip_reason_names_what_is_missing(peer, tmp_path):
    src = tmp_path / "peer"
    src.mkdir()
    frame = tmp_path / "frame"
    for d in ("CALIB", "CAM1", "FG1"):
        (frame / d).mkdir(parents=True)
    assert "no C++ compiler" in peer.skip_reason(src, frame, None)
    assert "build.sh missing" in peer.skip_reason(src, frame, "/usr/bin/g++")
    (src / "build.sh").write_text("#!/bin/sh\n")
    assert peer.skip_reason(src, frame, "/usr/bin/g++") is None
    (frame / "FG1").rmdir()
    assert "FG1 missing" in peer.skip_reason(src, frame, "/usr/bin/g++")
    assert "CALIB, CAM1, FG1 missing" in peer.skip_reason(src, tmp_path / "none", "g++")


def test_peer_unavailable_without_sources(peer, tmp_path):
    with pytest.raises(peer.PeerUnavailable, match="sources"):
        peer.Peer(tmp_path / "no_peer", tmp_path)


def test_build_failure_quotes_the_compiler(peer, tmp_path):
    src = tmp_path / "peer"
    src.mkdir()
    (src / "build.sh").write_text("echo 'src/main.cpp:1: error: boom' >&2\nexit 1\n")
    with pytest.raises(peer.PeerUnavailable, match="exit status 1.*boom"):
        peer.build(src, tmp_path / "out")


def test_anneal_only_cancels_the_fixed_part(peer):
    # fixed 30 ms + 2 ms per layer: K layers cost 2 K ms whatever the fixed part
    for fixed in (0.0, 0.03, 0.5):
        t15, t1 = fixed + 15 * 0.002, fixed + 0.002
        assert peer.anneal_only(t15, t1, 15) == pytest.approx(0.030)
    with pytest.raises(ValueError, match="layers"):
        peer.anneal_only(0.1, 0.05, 1)
