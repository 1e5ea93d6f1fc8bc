"""RealSense recordings: the real D435 .bag, and .db3 fixtures recorded at test time by librealsense."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.core.camera_model import StreamInfo
from depthstation.core.capture.importer import import_recordings
from depthstation.core.capture.registry import open_inputs, open_recording
from depthstation.core.capture.rs_writer import write_realsense_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.errors import InputError


def assert_same_info(a: StreamInfo, b: StreamInfo, tol: float = 1e-6) -> None:
    """Intrinsics (relative), distortion, extrinsics and depth units agree to `tol`."""
    for x, y in ((a.depth_intrinsics, b.depth_intrinsics), (a.color_intrinsics, b.color_intrinsics)):
        assert x is not None and y is not None
        assert (x.width, x.height, x.model) == (y.width, y.height, y.model)
        np.testing.assert_allclose([x.fx, x.fy, x.ppx, x.ppy], [y.fx, y.fy, y.ppx, y.ppy], rtol=tol)
        np.testing.assert_allclose(x.coeffs, y.coeffs, atol=tol)
    np.testing.assert_allclose(a.depth_to_color.matrix, b.depth_to_color.matrix, atol=tol)
    assert a.depth_units_m == pytest.approx(b.depth_units_m, rel=tol)


def test_real_d435_bag(d435_bag: Path) -> None:
    rec = open_recording(d435_bag)
    assert rec.name == "single_depth_color_640x480"
    assert rec.frame_count == 2
    assert rec.stream_counts == {"depth": 2, "color": 1}
    info = rec.info
    assert info.depth_units_m == pytest.approx(0.001, rel=1e-6)
    assert info.baseline_m == pytest.approx(0.05017, abs=1e-5)
    assert info.depth_intrinsics.fx == pytest.approx(390.43, abs=0.01)
    assert (info.depth_intrinsics.width, info.depth_intrinsics.height) == (640, 480)
    assert info.color_intrinsics is not None and info.color_intrinsics.fx == pytest.approx(613.20, abs=0.01)
    assert info.device["serial_number"] == "728612070259"
    frames = list(rec.frames())
    assert [f.index for f in frames] == [169, 170]
    assert sum(f.color is not None for f in frames) == 1
    assert all(f.depth is not None and f.depth.shape == (480, 640) for f in frames)
    # Walls 0.45 to 2.2 m away: the median valid depth must lie in that range.
    d = frames[0].depth_m(info.depth_units_m)
    assert 0.45 < float(np.nanmedian(d)) < 2.2
    # Geometry agrees with librealsense's own playback of the same file.
    import pyrealsense2 as rs

    cfg = rs.config()
    cfg.enable_device_from_file(str(d435_bag), repeat_playback=False)
    pipe = rs.pipeline()
    prof = pipe.start(cfg)
    try:
        e = prof.get_stream(rs.stream.depth).get_extrinsics_to(prof.get_stream(rs.stream.color))
        from depthstation.core.camera_model import Extrinsics

        ref = Extrinsics.from_librealsense(e.rotation, e.translation)
        np.testing.assert_allclose(info.depth_to_color.matrix, ref.matrix, atol=1e-6)
        fs = pipe.wait_for_frames(5000)
        np.testing.assert_array_equal(np.asanyarray(fs.get_depth_frame().get_data()), frames[1].depth)
    finally:
        pipe.stop()


@pytest.fixture()
def db3(tmp_path: Path) -> tuple[Path, list]:  # type: ignore[type-arg]
    info = sample_info(64, 48, infrared=True)
    frames = list(sample_frames(info, 4, seed=7, start_ns=1_700_000_000_000_000_000))
    path = tmp_path / "standpoint_07.db3"
    assert write_realsense_recording(path, info, frames) == 4
    return path, frames


def test_db3_record_import_read_is_bit_exact(db3: tuple[Path, list], tmp_path: Path) -> None:  # type: ignore[type-arg]
    path, frames = db3
    info = sample_info(64, 48)
    rec = open_recording(path)
    assert rec.frame_count == 4
    assert_same_info(rec.info, info)
    assert rec.info.baseline_m == pytest.approx(0.095, rel=1e-6)
    assert rec.info.device["serial_number"] == "000000000001"
    session = import_recordings([path], tmp_path / "session")
    assert [e["status"] for e in session.standpoints] == ["complete"]
    (mrec,) = open_inputs([tmp_path / "session"])
    assert mrec.name == "standpoint_07"
    assert_same_info(mrec.info, info)
    got = list(mrec.frames())
    assert [f.index for f in got] == [f.index for f in frames]
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_array_equal(a.infrared, b.infrared)
        assert abs(a.timestamp_ns - b.timestamp_ns) < 1000  # ms double in the file: sub-microsecond


def test_a_depth_only_db3_reads_back(tmp_path: Path) -> None:
    """A capture without colour frames from a camera that has a colour sensor, exported or
    simulated as .db3, was unreadable by our own reader (KeyError ''; an empty topic list asked
    for every message), which the export then reported as a full disk."""
    from dataclasses import replace

    info = sample_info(64, 48)  # the colour sensor is declared, its stream never delivers
    frames = [replace(f, color=None) for f in sample_frames(info, 3, seed=4, start_ns=1_700_000_000_000_000)]
    path = tmp_path / "depth_only.db3"
    assert write_realsense_recording(path, info, frames) == 3
    rec = open_recording(path)
    got = list(rec.frames())
    assert len(got) == 3
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        assert b.color is None


def test_write_realsense_refuses_bag_and_overwrite(db3: tuple[Path, list], tmp_path: Path) -> None:  # type: ignore[type-arg]
    info = sample_info(64, 48)
    with pytest.raises(InputError, match=r"\.db3"):
        write_realsense_recording(tmp_path / "x.bag", info, sample_frames(info, 1))
    with pytest.raises(InputError, match="never overwritten"):
        write_realsense_recording(db3[0], info, sample_frames(info, 1))


def test_png_dataset(charuco_dir: Path) -> None:
    recs = open_inputs([charuco_dir])
    assert [r.name for r in recs][:2] == ["pose03", "pose04"]
    rec = recs[0]
    assert rec.info.depth_aligned_to_color
    assert rec.info.depth_intrinsics == rec.info.color_intrinsics
    assert rec.info.depth_intrinsics.fx == pytest.approx(1377.6449, abs=1e-3)
    assert np.allclose(rec.info.depth_to_color.matrix, np.eye(4))
    fs = next(rec.frames())
    assert fs.index == 0 and fs.depth is not None and fs.depth.dtype == np.uint16
    assert fs.depth.shape == (1080, 1920) and fs.color is not None and fs.color.shape == (1080, 1920, 3)
    # A single standpoint folder opens on its own too (camera.json one level up).
    assert open_recording(charuco_dir / "pose05").frame_count == rec.frame_count


def _copy_to_rosbag2_dir(src: Path, out: Path, drop: str | None = None) -> None:
    """Re-store a librealsense .db3 as a rosbag2 directory (metadata.yaml + db3), optionally without
    the topics containing `drop`."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([src], default_typestore=ts) as r, Writer(out, version=8) as w:
        conns = {
            c.id: w.add_connection(c.topic, c.msgtype, typestore=ts)
            for c in r.connections
            if drop is None or drop not in c.topic
        }
        for c, t, raw in r.messages():
            if c.id in conns:
                w.write(conns[c.id], t, raw)


def test_rosbag2_directory_and_missing_depth(db3: tuple[Path, list], tmp_path: Path) -> None:  # type: ignore[type-arg]
    path, frames = db3
    bagdir = tmp_path / "standpoint_08"
    _copy_to_rosbag2_dir(path, bagdir)
    rec = open_recording(bagdir)
    assert rec.name == "standpoint_08" and rec.frame_count == 4
    for a, b in zip(frames, rec.frames(), strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.color, b.color)
    nodepth = tmp_path / "nodepth"
    _copy_to_rosbag2_dir(path, nodepth, drop="Depth_0/image")
    with pytest.raises(InputError, match="no depth"):
        open_recording(nodepth)


def test_a_colour_frame_two_depth_frames_share_reaches_both_without_holding_the_file() -> None:
    """Colour at 15 fps beside depth at 30 fps (or a dropped colour frame): two depth frames pair
    with one colour frame. Both get it, and each frame set leaves as soon as its images are read;
    taking the image away at the first depth frame left the second without colour and kept every
    later frame in memory to the end of the file."""
    from depthstation.core.capture.realsense_bag import assemble

    n = 12
    depth_t = [1000 * k for k in range(n)]
    colour_t = [1000 * k + 5 for k in range(0, n, 2)]
    pairing = {("depth", t): {"color": colour_t[k // 2]} for k, t in enumerate(depth_t)}
    order = sorted([("depth", t) for t in depth_t] + [("color", t) for t in colour_t], key=lambda m: m[1])
    read: list[int] = []
    loaded: list[tuple[str, int]] = []

    def messages():  # type: ignore[no-untyped-def]
        for i, (kind, t) in enumerate(order):
            read.append(i)
            yield kind, t, lambda kind=kind, t=t: (loaded.append((kind, t)), np.full(2, t))[1]

    out = []
    for t, parts in assemble(messages(), pairing, depth_t[2:]):   # from the third frame, as `start=2`
        out.append((t, int(parts["color"][0]), len(read)))
        parts["color"][:] = -1          # a user changing its frame set in place changes no other
    assert [t for t, _, _ in out] == depth_t[2:]
    assert [c for _, c, _ in out] == [colour_t[k // 2] for k in range(2, n)]
    # each frame set leaves once its own messages are read: no frame waits for later ones
    last_needed = {t: max(order.index(("depth", t)), order.index(("color", colour_t[k // 2])))
                   for k, t in enumerate(depth_t)}
    assert all(seen == last_needed[t] + 1 for t, _, seen in out)
    # the colour frame only the skipped first two depth frames wanted is not even decoded; the
    # others once each
    assert ("color", colour_t[0]) not in loaded
    expect = [("depth", t) for t in depth_t[2:]] + [("color", t) for t in colour_t[1:]]
    assert sorted(loaded) == sorted(expect)
