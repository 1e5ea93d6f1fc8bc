"""Our MCAP format and session directory: round trip, recovery, refusal to overwrite, interoperability."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.capture.mcap_reader import McapRecording
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.registry import open_inputs, open_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.capture.session import Session
from depthstation.core.errors import InputError


def test_mcap_round_trip_is_bit_exact(tmp_path: Path) -> None:
    info = sample_info(infrared=True)
    frames = list(sample_frames(info, 5, seed=1))
    path = tmp_path / "standpoint_01.mcap"
    meta = {"standpoint": {"distance_m": 1.0, "inclination_deg": 30.0}, "calibration": {"state": "factory"}}
    assert write_mcap(path, info, frames, meta, temperatures=[(frames[0].timestamp_ns, {"asic": 41.5})]) == 5
    rec = open_recording(path)
    assert rec.name == "standpoint_01"
    assert rec.frame_count == 5
    assert rec.info == info  # exact: stored as a JSON metadata record
    assert rec.metadata["standpoint"] == meta["standpoint"]
    assert rec.metadata["device"]["name"] == "Intel RealSense D455"
    got = list(rec.frames())
    assert [f.index for f in got] == [f.index for f in frames]
    for a, b in zip(frames, got, strict=True):
        assert a.timestamp_ns == b.timestamp_ns
        assert b.depth is not None and b.depth.dtype == np.uint16
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.infrared, b.infrared)
        assert b.metadata == a.metadata
    assert [f.index for f in rec.frames(start=2, limit=2)] == [2, 3]
    assert rec.temperatures() == {"asic": ([frames[0].timestamp_ns], [41.5])}


def test_write_refuses_to_overwrite(tmp_path: Path) -> None:
    info = sample_info()
    path = tmp_path / "a.mcap"
    write_mcap(path, info, sample_frames(info, 1))
    before = path.read_bytes()
    with pytest.raises(InputError, match="never overwritten"):
        write_mcap(path, info, sample_frames(info, 2))
    assert path.read_bytes() == before


def test_truncated_mcap_recovers_complete_chunks(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    info = sample_info(32, 24)
    frames = list(sample_frames(info, 40, seed=2))
    full = tmp_path / "full.mcap"
    from depthstation.core.capture.mcap_writer import McapFileWriter

    with McapFileWriter(full, info, compression="lz4", chunk_size=8 * 1024) as w:
        for f in frames:
            w.write(f)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    rec = open_recording(cut)
    assert rec.frame_count is None  # no summary in a cut file
    with caplog.at_level(logging.WARNING, logger="depthstation.core.capture"):
        got = list(rec.frames())
    # Every frame whose chunk survived: count the complete chunks independently.
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with full.open("rb") as fh:
        n_expected = 0
        for r in StreamReader(fh, emit_chunks=True).records:
            if isinstance(r, Chunk) and r.data and fh.tell() <= len(data) // 2:
                n_expected = max(n_expected, r.message_end_time)
    survived = [fr for fr in frames if fr.timestamp_ns <= n_expected]
    assert 5 < len(got) < 40
    assert len(survived) - 1 <= len(got) <= len(survived)  # the last frame may straddle the cut
    for a, b in zip(frames, got, strict=False):
        np.testing.assert_array_equal(a.depth, b.depth)
    assert isinstance(rec, McapRecording) and rec.truncated and rec.recovered_frames == len(got)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert str(cut) in warnings[0] and f"recovered {len(got)} frames" in warnings[0]


def test_not_a_recording_is_input_error(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world, no mcap here")
    with pytest.raises(InputError):
        open_recording(junk)
    other = tmp_path / "notes.txt"
    other.write_text("x")
    with pytest.raises(InputError):
        open_recording(other)


def test_mcap_without_depth_is_input_error(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "nodepth.mcap"
    with path.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        w.add_metadata("streams", {"json": json.dumps(sample_info().to_dict())})
        w.finish()
    with pytest.raises(InputError, match="no depth"):
        open_recording(path)


def test_session_lifecycle_crash_and_resume(tmp_path: Path) -> None:
    info = sample_info(32, 24)
    sdir = tmp_path / "session"
    s = Session.create(sdir, device={"name": "D455"}, protocol={"name": "demo"})
    with pytest.raises(InputError):
        Session.create(sdir)
    with s.standpoint_writer("standpoint_01", info, {"distance_m": 1.0}) as w:
        for f in sample_frames(info, 4):
            assert w.write(f)
        w.write_temperature(1, {"asic": 40.0})
        w.update_standpoint(measured_distance_m=1.02)
    assert w.dropped == 0
    assert (sdir / "standpoint_01.mcap").is_file()
    assert s.status("standpoint_01") == "complete"
    with pytest.raises(InputError):
        s.standpoint_writer("standpoint_01", info, {})
    # A crash mid-standpoint: another process writes standpoint_02 and dies without closing.
    script = (
        "import os, sys\n"
        "from depthstation.core.capture.session import Session\n"
        "from depthstation.core.capture.sample_recordings import sample_frames, sample_info\n"
        "info = sample_info(32, 24)\n"
        "w = Session.open(sys.argv[1]).standpoint_writer('standpoint_02', info, {'distance_m': 1.5})\n"
        "for f in sample_frames(info, 3):\n"
        "    w.write(f)\n"
        "os._exit(9)\n"
    )
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", script, str(sdir)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 9, proc.stderr
    on_disk = json.loads((sdir / "session.json").read_text())
    assert [e["status"] for e in on_disk["standpoints"]] == ["complete", "recording"]
    s2 = Session.open(sdir)
    assert [e["status"] for e in s2.standpoints] == ["complete", "partial"]
    assert (sdir / "standpoint_02.mcap.partial").is_file()
    recs = open_inputs([sdir])
    assert [r.name for r in recs] == ["standpoint_01"]
    assert recs[0].metadata["standpoint"] == {
        "distance_m": 1.0,
        "measured_distance_m": 1.02,
        "name": "standpoint_01",
    }
    assert s2.standpoints[0]["standpoint"]["measured_distance_m"] == 1.02
    assert recs[0].metadata["protocol"] == {"name": "demo"}
    # Resume: re-record standpoint_02; the crashed attempt is kept aside, not overwritten.
    with s2.standpoint_writer("standpoint_02", info, {"distance_m": 1.5}) as w3:
        for f in sample_frames(info, 2):
            w3.write(f)
    assert (sdir / "standpoint_02.attempt-1.mcap.partial").is_file()
    assert s2.status("standpoint_02") == "complete"
    assert [r.name for r in Session.open(sdir).recordings()] == ["standpoint_01", "standpoint_02"]
    s2.discard("standpoint_01", "board moved")
    assert s2.status("standpoint_01") == "discarded"
    assert any(p.name.startswith("standpoint_01.discarded") for p in sdir.iterdir())


def test_writer_queue_full_drops_and_counts(tmp_path: Path) -> None:
    info = sample_info(32, 24)
    s = Session.create(tmp_path / "s")
    w = s.standpoint_writer("sp", info, {}, queue_frames=1)
    import threading

    gate = threading.Event()
    real_write = w._writer.write

    def slow_write(fs):  # type: ignore[no-untyped-def]
        gate.wait(5)
        real_write(fs)

    w._writer.write = slow_write  # type: ignore[method-assign]
    results = [w.write(f) for f in sample_frames(info, 5)]
    gate.set()
    w.close()
    assert results[0] is True and False in results
    assert w.dropped == results.count(False)
    assert w.max_put_s < 0.05  # write() never waited on the slow disk
    assert s.standpoints[0]["dropped_frames"] == w.dropped


def test_rosbags_anyreader_opens_our_mcap(tmp_path: Path) -> None:
    from rosbags.highlevel import AnyReader

    info = sample_info()
    frames = list(sample_frames(info, 2))
    path = tmp_path / "x.mcap"
    write_mcap(path, info, frames)
    with AnyReader([path]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics["/camera/depth/image_rect_raw"] == "sensor_msgs/msg/Image"
        assert topics["/camera/depth/camera_info"] == "sensor_msgs/msg/CameraInfo"
        assert topics["/tf_static"] == "tf2_msgs/msg/TFMessage"
        conns = [c for c in reader.connections if c.topic == "/camera/depth/image_rect_raw"]
        msgs: list[Any] = [
            reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)
        ]
        assert msgs[0].encoding == "16UC1"
        np.testing.assert_array_equal(np.frombuffer(msgs[0].data, np.uint16).reshape(48, 64), frames[0].depth)
        ci: list[Any] = [
            reader.deserialize(raw, c.msgtype)
            for c, _, raw in reader.messages(
                connections=[c for c in reader.connections if c.topic == "/camera/color/camera_info"]
            )
        ]
        assert ci[0].k[0] == pytest.approx(info.color_intrinsics.fx)  # type: ignore[union-attr]
        tf: list[Any] = [
            reader.deserialize(raw, c.msgtype)
            for c, _, raw in reader.messages(
                connections=[c for c in reader.connections if c.topic == "/tf_static"]
            )
        ]
        # /tf_static is realsense-ros' tree under camera_link, stamped at the first frame; the chain
        # depth optical -> link -> colour optical gives the depth-to-colour extrinsics
        from depthstation.core.capture.ros_bag import tf_between
        from depthstation.core.capture.rosmsgs import extrinsics_from_transform

        assert len(tf) == 1
        tree = {str(t.child_frame_id): (str(t.header.frame_id), extrinsics_from_transform(t.transform))
                for t in tf[0].transforms}
        assert {p for p, _ in tree.values()} >= {"camera_link"}
        assert all(t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == frames[0].timestamp_ns
                   for t in tf[0].transforms)
        e = tf_between(tree, "camera_depth_optical_frame", "camera_color_optical_frame")
        assert e is not None
        np.testing.assert_allclose(e.matrix, info.depth_to_color.matrix, atol=1e-12)
        qos = next(c.ext.offered_qos_profiles for c in reader.connections if c.topic == "/tf_static")
        assert qos[0].durability.name == "TRANSIENT_LOCAL" and qos[0].depth == 1


def test_rerun_mcap_importer_sees_depth_image_with_pinhole(tmp_path: Path) -> None:
    """Rerun's own MCAP importer (the CLI the viewer uses) decodes a DepthImage under a Pinhole."""
    import re
    import shutil
    import subprocess
    import sys

    exe = Path(sys.executable).parent / "rerun"
    if not exe.exists():
        found = shutil.which("rerun")
        if found is None:
            pytest.skip("rerun CLI not installed")
        exe = Path(found)
    info = sample_info()
    path = tmp_path / "x.mcap"
    write_mcap(path, info, sample_frames(info, 2))
    rrd = tmp_path / "x.rrd"
    subprocess.run(
        [str(exe), "mcap", "convert", str(path), "-o", str(rrd)], check=True, capture_output=True, timeout=120
    )
    text = subprocess.run(
        [str(exe), "rrd", "print", "-vvv", str(rrd)], check=True, capture_output=True, text=True, timeout=120
    ).stdout
    depth_rows = [
        ln for ln in text.splitlines() if "channel_datatype" in ln and "camera_depth_optical_frame" in ln
    ]
    assert len(depth_rows) == 2  # one DepthImage per frame, in the depth camera's image plane
    assert "DepthImage:buffer" in text
    pinhole = [
        ln
        for ln in text.splitlines()
        if "[camera_depth_optical_frame_image_plane]" in ln and "[camera_depth_optical_frame]" in ln
    ]
    assert pinhole, "no Pinhole from the depth CameraInfo"
    fx = float(re.search(r"\[\[([0-9.]+), 0\.0", pinhole[0]).group(1))  # type: ignore[union-attr]
    assert fx == pytest.approx(info.depth_intrinsics.fx, rel=1e-5)
