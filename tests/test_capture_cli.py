"""`depthstation capture ...` through the real console script: tables, JSON, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from depthstation.core.capture.mcap_writer import McapFileWriter
from depthstation.core.capture.sample_recordings import sample_frames, sample_info

EXE = str(Path(sys.executable).parent / "depthstation")


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([EXE, "capture", *args], capture_output=True, text=True, timeout=120)


def test_import_and_info_of_real_bag(d435_bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "session"
    p = run("import", str(d435_bag), "--out", str(out))
    assert p.returncode == 0, p.stderr
    assert (out / "single_depth_color_640x480.mcap").is_file()
    p = run("info", str(out), "--json")
    assert p.returncode == 0, p.stderr
    (d,) = json.loads(p.stdout)
    assert d["frame_count"] == 2 and d["stream_counts"] == {"depth": 2, "color": 1}
    assert abs(d["info"]["baseline_m"] - 0.05017) < 1e-5
    assert abs(d["info"]["depth_intrinsics"]["fx"] - 390.43) < 0.01
    assert d["info"]["depth_units_m"] == 0.001
    assert d["duration_s"] > 0.1
    p = run("info", str(d435_bag))
    assert p.returncode == 0, p.stderr
    for text in ("390.431", "50.171 mm", "0.001 m", "depth: 2", "color: 1", "Intel RealSense D435"):
        assert text in p.stdout
    # Importing again into the same folder must not overwrite: one-line error, exit 2.
    p = run("import", str(d435_bag), "--out", str(out))
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1
    # One recording given twice (directly, or once as itself and once by another spelling) would be
    # two standpoints of the same frames, each weighing double in every study: refused.
    again = str(d435_bag.parent / ".." / d435_bag.parent.name / d435_bag.name)
    p = run("import", str(d435_bag), again, "--out", str(tmp_path / "twice"))
    assert p.returncode == 2 and "given twice" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "twice").exists()


def test_bad_inputs_exit_2_one_line(tmp_path: Path) -> None:
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    text = tmp_path / "readme.mcap"
    text.write_text("not an mcap")
    nodepth = tmp_path / "nodepth.mcap"
    from mcap.writer import Writer

    with nodepth.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        w.add_metadata("streams", {"json": json.dumps(sample_info().to_dict())})
        w.finish()
    for path in (junk, text, nodepth, tmp_path / "missing.mcap"):
        p = run("info", str(path))
        assert p.returncode == 2, (path, p.stderr)
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in p.stderr and str(path) in lines[0]
        if path == nodepth:
            assert "no depth" in lines[0]


def test_truncated_mcap_info_warns_once(tmp_path: Path) -> None:
    info = sample_info(32, 24)
    full = tmp_path / "full.mcap"
    with McapFileWriter(full, info, chunk_size=8 * 1024) as w:
        for f in sample_frames(info, 30):
            w.write(f)
    cut = tmp_path / "standpoint_09.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    p = run("info", str(cut), "--json")
    assert p.returncode == 0, p.stderr
    (d,) = json.loads(p.stdout)
    assert 0 < d["frames_read"] < 30
    warn = [line for line in p.stderr.splitlines() if "recovered" in line]
    assert len(warn) == 1 and str(cut) in warn[0] and f"recovered {d['frames_read']} frames" in warn[0]


def test_compact_rewrites_with_zstd(tmp_path: Path) -> None:
    info = sample_info(32, 24)
    src = tmp_path / "a.mcap"
    from depthstation.core.capture.mcap_writer import write_mcap

    frames = list(sample_frames(info, 3))
    write_mcap(src, info, frames, {"standpoint": {"distance_m": 2.0}})
    p = run("compact", str(src), str(tmp_path / "b.mcap"))
    assert p.returncode == 0, p.stderr
    from depthstation.core.capture.registry import open_recording

    rec = open_recording(tmp_path / "b.mcap")
    assert rec.metadata["standpoint"] == {"distance_m": 2.0}
    assert all(
        np.array_equal(np.asarray(a.depth), np.asarray(b.depth))
        for a, b in zip(frames, rec.frames(), strict=True)
    )


def test_a_session_with_no_complete_standpoint_is_refused_by_every_capture_command(tmp_path: Path) -> None:
    """A session whose only standpoint ended partial (the board never held still long enough):
    import crashed (IndexError, exit 1), export wrote an empty folder and info printed nothing."""
    from depthstation.core.capture.session import Session

    sess = tmp_path / "part"
    session = Session.create(sess)
    info = sample_info(64, 48)
    with session.standpoint_writer("standpoint_01", info, {}) as w:
        for fs in sample_frames(info, 3, seed=1):
            w.write(fs)
        w.close(ok=False)  # what a capture that gave up leaves: a partial standpoint
    assert [e["status"] for e in Session.open(sess).standpoints] == ["partial"]
    for args in (["capture", "import", str(sess), "--out", str(tmp_path / "i")],
                 ["capture", "export", str(sess), "--to", "tum", "--out", str(tmp_path / "e")],
                 ["capture", "info", str(sess)]):
        r = subprocess.run([EXE, *args], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, (args, r.stderr)
        assert "no complete standpoint" in r.stderr and "standpoint_01 partial" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "i").exists() and not (tmp_path / "e").exists()


def test_compact_writes_only_under_an_mcap_name(tmp_path: Path) -> None:
    """`compact a.mcap arch.db3` wrote an MCAP no reader took for one (exit 0, then exit 2 reading it)."""
    src = tmp_path / "a.mcap"
    info = sample_info(64, 48)
    with McapFileWriter(src, info) as w:
        for fs in sample_frames(info, 2, seed=2):
            w.write(fs)
    r = subprocess.run([EXE, "capture", "compact", str(src), str(tmp_path / "arch.db3")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "arch.db3" in r.stderr and ".mcap suffix" in r.stderr, r.stderr
    assert not (tmp_path / "arch.db3").exists()
