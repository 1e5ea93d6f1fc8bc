"""ROS recordings as users hold them (written here with rosbags' own writers in realsense-ros
layouts): the checkerboard study of a bag equals that of the same frames in our MCAP; depth-only
and namespaced bags open; a bag without depth says which topics it saw; our MCAP's time range and
its rewrite by a ROS tool; `capture export` read back."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from console import run_console as _cli
from ros_bags import write_bag

from depthstation.core.camera_model import Extrinsics
from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import open_inputs, open_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.capture.topics import TopicChoice

FIGURES = ("distance_m", "inclination_deg", "noise_m", "accuracy_m", "accuracy_rms_m", "fill_rate")
NAMES = ["standpoint_01", "standpoint_05"]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Two simulated standpoints (3 frames each) in our MCAP and their checkerboard table."""
    pytest.importorskip("open3d")
    from depthstation.core.protocol import load_protocol
    from depthstation.simulate.checkerboard_session import simulate_checkerboard

    proto = load_protocol("demo-d455")
    root = tmp_path_factory.mktemp("ros")
    out = simulate_checkerboard(proto, "d455-ideal", root / "sim", frames=3, standpoints=NAMES, seed=3)
    recs = sorted(open_inputs([out]), key=lambda r: r.name)
    return {"root": root, "board": proto.board, "recs": recs, "rows": [_row(r, proto.board) for r in recs]}


def _row(rec: Recording, board: Any) -> dict[str, float]:
    from depthstation.evaluate.checkerboard.study import evaluate_recording

    r = evaluate_recording(rec, board, frames=3)
    assert r.frames_used == 3, r.rejected
    return {k: float(r.figures[k]) for k in FIGURES}


def _same_geometry(a: Recording, b: Recording) -> None:
    ia, ib = a.info, b.info
    for x, y in ((ia.depth_intrinsics, ib.depth_intrinsics), (ia.color_intrinsics, ib.color_intrinsics)):
        assert x is not None and y is not None
        np.testing.assert_allclose([y.fx, y.fy, y.ppx, y.ppy], [x.fx, x.fy, x.ppx, x.ppy], rtol=1e-6)
        np.testing.assert_allclose(y.coeffs, x.coeffs, atol=1e-6)
        assert (y.width, y.height) == (x.width, x.height)
    np.testing.assert_allclose(ib.depth_to_color.matrix, ia.depth_to_color.matrix, atol=1e-6)
    assert ib.depth_units_m == ia.depth_units_m
    assert ib.baseline_m == pytest.approx(ia.baseline_m, rel=1e-6)


@pytest.mark.parametrize("layout", [
    {"ros": 2, "storage": "mcap"},
    {"ros": 2, "storage": "sqlite3", "compressed": True, "extrinsics_topic": True},
    {"ros": 1, "namespace": "/camera/"},
])
def test_bag_evaluates_like_our_mcap(simulated: dict[str, Any], layout: dict[str, Any]) -> None:
    root: Path = simulated["root"]
    tag = "_".join(f"{k}{v}" for k, v in layout.items() if k != "namespace").replace("/", "")
    for rec, row in zip(simulated["recs"], simulated["rows"], strict=True):
        path = root / f"{rec.name}_{tag}" if layout["ros"] == 2 else root / f"{rec.name}_{tag}.bag"
        write_bag(path, rec.info, rec.frames(), **layout)
        bag = open_recording(path)
        assert type(bag).__name__ == "RosRecording" and bag.frame_count == 3
        _same_geometry(rec, bag)
        got = _row(bag, simulated["board"])
        for k in FIGURES:
            assert got[k] == pytest.approx(row[k], rel=1e-6, abs=1e-9), (rec.name, tag, k)


def test_depth_only_bag_under_another_namespace(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = sample_info(infrared=True)
    frames = list(sample_frames(info, 3, seed=4))
    path = tmp_path / "robot"
    write_bag(path, info, frames, namespace="/robot1/D455_1/", depth_only=True, frame_prefix="D455_1")
    rec = open_recording(path)
    assert rec.stream_counts == {"depth": 3} and rec.info.color_intrinsics is None
    assert rec.metadata["source"]["topics"] == {"depth": "/robot1/D455_1/depth/image_rect_raw"}
    for a, b in zip(frames, rec.frames(), strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        assert a.timestamp_ns == b.timestamp_ns and b.color is None
    assert rec.info.baseline_m == pytest.approx(0.095, rel=1e-9)  # from the infra2 TF of the tree
    code, out, err = _cli(["capture", "info", str(path), "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)[0]["frames_read"] == 3


def test_topics_by_name_and_colour_stamps_apart(tmp_path: Path) -> None:
    """An unusual name needs --depth-topic; colour 7 ms after depth still pairs, and its stamp is kept."""
    info = sample_info()
    frames = list(sample_frames(info, 3, seed=5))
    path = tmp_path / "odd"
    write_bag(path, info, frames, namespace="/cams/front/", color_offset_ns=7_000_000, depth_float=True,
              compressed=True)
    rec = open_recording(path, topics=TopicChoice(depth="/cams/front/depth/image_rect_raw/compressedDepth"))
    got = list(rec.frames())
    assert len(got) == 3 and all(f.color is not None for f in got)
    assert got[1].metadata["stream_timestamps_ns"]["color"] == frames[1].timestamp_ns + 7_000_000
    np.testing.assert_allclose(rec.info.depth_to_color.matrix, info.depth_to_color.matrix, atol=1e-12)
    # 32FC1 through compressedDepth (inverse depth, quantised): finer than 1 mm, so read at 0.1 mm
    # counts (ros_bag.depth_units_for), within its step; beyond 6.55 m, their range, no depth
    assert rec.info.depth_units_m == pytest.approx(1e-4)
    a, b = frames[0].depth, got[0].depth * rec.info.depth_units_m * 1000.0   # mm
    keep = (a > 200) & (a < 6500)
    step_mm = (a[keep] / 1000.0) ** 2 / (100 * 101 / 1000.0)
    assert np.all(np.abs(b[keep] - a[keep]) <= step_mm + 0.1)
    assert not np.any(b[a > 6600])


def test_one_topic_for_two_streams_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The depth topic given as --color-topic made an import of 0 frames with exit 0; the colour
    given as --infrared-topic stored RGB as infrared."""
    info = sample_info()
    path = tmp_path / "std"
    write_bag(path, info, list(sample_frames(info, 2, seed=5)))
    depth, colour = "/camera/camera/depth/image_rect_raw", "/camera/camera/color/image_raw"
    for option, topic, words in (("--color-topic", depth, "both depth and color"),
                                 ("--infrared-topic", colour, "both color and infrared")):
        code, _, err = _cli(["capture", "import", str(path), option, topic, "--out", str(tmp_path / "o")],
                            capsys)
        assert code == 2 and words in err and option in err and "Traceback" not in err, err
        assert not (tmp_path / "o").exists()


def test_images_of_another_size_than_their_camera_info(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Colour at half the size its camera_info gives was read with those intrinsics (the board's
    pixels on the wrong rays, blamed later on the square length); PNG sets refuse the same."""
    import dataclasses

    info = sample_info()
    frames = [dataclasses.replace(f, color=np.ascontiguousarray(f.color[::2, ::2]))
              for f in sample_frames(info, 2, seed=5)]
    path = tmp_path / "half"
    write_bag(path, info, frames)
    code, _, err = _cli(["capture", "info", str(path)], capsys)
    c = info.color_intrinsics
    assert code == 2 and f"its camera_info says {c.width}x{c.height}" in err and "Traceback" not in err, err


def test_repeated_depth_stamps_are_warned(tmp_path: Path) -> None:
    """Colour pairs with depth by header stamp: two depth frames at one stamp took the same colour
    frame without a word."""
    import dataclasses

    from depthstation.core.run_warnings import collecting

    info = sample_info()
    frames = list(sample_frames(info, 3, seed=5))
    frames[2] = dataclasses.replace(frames[2], timestamp_ns=frames[1].timestamp_ns)
    write_bag(tmp_path / "rep", info, frames)
    with collecting() as found:
        assert len(list(open_recording(tmp_path / "rep").frames())) == 3
    assert [w.code for w in found] == ["ros-stamps"]
    write_bag(tmp_path / "ok", info, list(sample_frames(info, 3, seed=5)))
    with collecting() as found:
        list(open_recording(tmp_path / "ok").frames())
    assert found == []


def test_bag_without_depth_names_the_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "colour_only"
    with Writer(path, version=8) as w:
        c = w.add_connection("/camera/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        T = ts.types
        msg = T["sensor_msgs/msg/Image"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                            frame_id="x"),
            height=1, width=1, encoding="rgb8", is_bigendian=0, step=3, data=np.zeros(3, np.uint8))
        w.write(c, 10**9, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    code, _, err = _cli(["capture", "info", str(path)], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "/camera/camera/color/image_raw" in lines[0] and "--depth-topic" in lines[0]
    assert "Traceback" not in err
    code, _, err = _cli(["capture", "info", str(path), "--depth-topic", "/nope"], capsys)
    assert code == 2 and "/nope" in err and "/camera/camera/color/image_raw" in err


def test_our_mcap_time_range_and_rewrite(simulated: dict[str, Any]) -> None:
    """No message at 1970: the summary's range is the frames' span; a rosbags rewrite (the MCAP's
    metadata records gone) still reads and evaluates identically."""
    from mcap.reader import make_reader
    from ros_bags import rewrite

    rec = simulated["recs"][1]
    stamps = [f.timestamp_ns for f in rec.frames()]
    with rec.path.open("rb") as fh:
        stats = make_reader(fh).get_summary().statistics
    assert (stats.message_start_time, stats.message_end_time) == (min(stamps), max(stamps))
    out = rewrite(rec.path, simulated["root"] / "rewritten")
    again = open_recording(out)
    assert type(again).__name__ == "RosRecording"
    _same_geometry(rec, again)
    assert [f.index for f in again.frames()] == [f.index for f in rec.frames()]
    got = _row(again, simulated["board"])
    for k in FIGURES:
        assert got[k] == pytest.approx(simulated["rows"][1][k], rel=1e-6, abs=1e-9), k


def test_export_rosbag2_and_db3_read_back(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = sample_info(infrared=True)
    frames = list(sample_frames(info, 3, seed=6))
    src = tmp_path / "a.mcap"
    write_mcap(src, info, frames)
    code, _, err = _cli(["capture", "export", str(src), "--to", "rosbag2", "--out", str(tmp_path / "ros")],
                        capsys)
    assert code == 0, err
    bag = open_recording(tmp_path / "ros" / "a")
    assert bag.metadata["source"]["topics"]["depth"] == "/camera/camera/depth/image_rect_raw"
    assert bag.metadata["source"]["extrinsics"] == "/camera/camera/extrinsics/depth_to_color"
    np.testing.assert_allclose(bag.info.depth_to_color.matrix, info.depth_to_color.matrix, atol=1e-12)
    for a, b in zip(frames, bag.frames(), strict=True):
        assert a.timestamp_ns == b.timestamp_ns
        for k in ("depth", "color", "infrared"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    code, _, err = _cli(["capture", "export", str(src), "--to", "rosbag2", "--out", str(tmp_path / "ros")],
                        capsys)
    assert code == 2 and "not empty" in err  # never overwrites
    # TUM: ORB-SLAM3's associations (rgb first, no comment), the infrared imager as 'rgb'
    code, _, err = _cli(["capture", "export", str(src), "--to", "tum", "--out", str(tmp_path / "tum")],
                        capsys)
    assert code == 0, err
    lines = (tmp_path / "tum" / "a" / "associations.txt").read_text().splitlines()
    assert len(lines) == 3 and all(len(x.split()) == 4 and x.split()[1].startswith("rgb/") for x in lines)
    import cv2

    rgb = cv2.imread(str(tmp_path / "tum" / "a" / lines[0].split()[1]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(rgb, frames[0].infrared)
    if sys.modules.get("pyrealsense2") is None:
        pytest.importorskip("pyrealsense2")
    code, _, err = _cli(["capture", "export", str(src), "--to", "db3", "--out", str(tmp_path / "rs")], capsys)
    assert code == 0, err
    rs = open_recording(tmp_path / "rs" / "a.db3")
    assert type(rs).__name__ == "RealsenseRecording"
    np.testing.assert_array_equal(next(rs.frames()).depth, frames[0].depth)


def test_export_rosbag2_writes_millimetres_whatever_the_units(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """16UC1 is millimetres (REP 118): depth in 100 um units came back 10x too far in ROS and here."""
    import dataclasses

    info = dataclasses.replace(sample_info(), depth_units_m=0.0001)
    frames = list(sample_frames(info, 2, seed=3))
    src = tmp_path / "fine.mcap"
    write_mcap(src, info, frames)
    code, _, err = _cli(["capture", "export", str(src), "--to", "rosbag2", "--out", str(tmp_path / "ros")],
                        capsys)
    assert code == 0 and "resolution reduced to 1 mm" in err, err
    bag = open_recording(tmp_path / "ros" / "fine")
    for a, b in zip(frames, bag.frames(), strict=True):
        z_src = a.depth.astype(np.float64) * 0.0001
        z_bag = b.depth.astype(np.float64) * bag.info.depth_units_m
        near = a.depth.astype(np.float64) * 0.1 <= 65535
        assert np.all(np.abs(z_bag - z_src)[near] <= 0.0005 + 1e-12)  # rounded to the millimetre


def test_tum_export_says_what_it_cannot_hold(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two frames at one time stamp wrote one PNG over the other, and depth beyond 13.1 m (TUM's
    5000 counts per metre in 16 bits) became 'no depth', both without a word."""
    import dataclasses

    info = sample_info()
    frames = list(sample_frames(info, 3, seed=4))
    frames[2] = dataclasses.replace(frames[2], timestamp_ns=frames[1].timestamp_ns)
    frames[0].depth[0, 0] = 14000  # 14 m in 1 mm units
    src = tmp_path / "a.mcap"
    write_mcap(src, info, frames)
    code, _, err = _cli(["capture", "export", str(src), "--to", "tum", "--out", str(tmp_path / "tum")],
                        capsys)
    assert code == 0, err
    assert "repeat an earlier frame's time stamp" in err and "1 pixels beyond 13.107 m" in err
    folder = tmp_path / "tum" / "a"
    lines = [x for x in (folder / "depth.txt").read_text().splitlines() if not x.startswith("#")]
    assert len(lines) == 2 and len(list((folder / "depth").iterdir())) == 2


def test_aligned_depth_keeps_its_baseline_and_stereo_imager(tmp_path: Path) -> None:
    """realsense-ros with align_depth stamps depth in the colour optical frame and publishes the
    imager's own intrinsics on depth/camera_info: the baseline (from /tf_static) and the stereo
    intrinsics that Intel's metrics need were lost (the frame prefix was looked for before 'depth')."""
    base = sample_info(64, 48)
    info = replace(base, depth_intrinsics=base.color_intrinsics, depth_aligned_to_color=True,
                   stereo_intrinsics=base.depth_intrinsics, depth_to_color=Extrinsics())
    frames = list(sample_frames(base, 2, seed=4))
    write_bag(tmp_path / "aligned", info, frames, aligned=True)
    bag = open_recording(tmp_path / "aligned")
    assert bag.metadata["source"]["topics"]["depth"].endswith("aligned_depth_to_color/image_raw")
    assert bag.info.depth_aligned_to_color
    assert bag.info.baseline_m == pytest.approx(base.baseline_m, abs=1e-9)
    assert bag.info.stereo_intrinsics is not None
    assert bag.info.stereo_intrinsics.fx == pytest.approx(base.depth_intrinsics.fx, rel=1e-6)


def test_export_of_an_aligned_png_set_keeps_baseline_and_stereo_imager(
        charuco_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The real D435 set (depth aligned to colour by the SDK): its rosbag2 export read back has the
    baseline and the unaligned depth intrinsics of camera.json (the dqt_* columns need both)."""
    png = open_recording(charuco_dir / "pose03")
    code, _, err = _cli(["capture", "export", str(charuco_dir / "pose03"), "--to", "rosbag2",
                         "--out", str(tmp_path / "ros")], capsys)
    assert code == 0, err
    bag = open_recording(tmp_path / "ros" / "pose03")
    assert png.info.baseline_m and bag.info.baseline_m == pytest.approx(png.info.baseline_m, abs=1e-9)
    assert png.info.stereo_intrinsics is not None and bag.info.stereo_intrinsics is not None
    for k in ("width", "height", "fx", "fy", "ppx", "ppy"):
        assert getattr(bag.info.stereo_intrinsics, k) == pytest.approx(getattr(png.info.stereo_intrinsics, k))



def test_a_topic_option_with_a_session_is_honoured_or_refused(simulated: dict[str, Any], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A session's standpoints are read from our writer's topics: a --depth-topic naming another was
    ignored (the study ran on the stream not asked for); naming the session's own one is the same run."""
    session = simulated["root"] / "sim"
    board = Path(__file__).parents[1] / "protocols" / "demo-d455.toml"
    args = ["evaluate", "checkerboard", str(session), "--board", str(board), "--frames", "2"]
    code, _, err = _cli([*args, "--out", str(tmp_path / "a"), "--depth-topic", "/cams/front/depth"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert str(session) in err and "/cams/front/depth" in err and "/camera/depth/image_rect_raw" in err
    assert not (tmp_path / "a").exists()
    own = ["--depth-topic", "/camera/depth/image_rect_raw"]
    code, _, err = _cli([*args, "--out", str(tmp_path / "b"), *own], capsys)
    assert code == 0, err


def test_reading_from_a_later_frame_keeps_few_colour_images_and_pairs_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames read from the middle of a bag (the figure frame, a fit sample): the colour images of
    the skipped frames are not all kept (they were: ~600 MB for the middle of a 1334-frame bag),
    and the start frame still gets its own colour, 7 ms after its depth."""
    from depthstation.core.capture import ros_bag

    info = sample_info()
    frames = list(sample_frames(info, 12, seed=6))
    path = tmp_path / "bag"
    write_bag(path, info, frames, color_offset_ns=7_000_000)
    monkeypatch.setattr(ros_bag, "PRE_START_KEEP", 2)
    kept: list[int] = []
    real_deque = ros_bag.deque

    class Watched(real_deque):  # type: ignore[misc, valid-type]
        def append(self, item: Any) -> None:
            super().append(item)
            kept.append(len(self))

    monkeypatch.setattr(ros_bag, "deque", Watched)
    rec = open_recording(path)
    got = list(rec.frames(start=9, limit=2))
    assert [f.timestamp_ns for f in got] == [frames[9].timestamp_ns, frames[10].timestamp_ns]
    for f, want in zip(got, frames[9:11], strict=True):
        assert f.metadata["stream_timestamps_ns"]["color"] == want.timestamp_ns + 7_000_000
        np.testing.assert_array_equal(f.color, want.color)
    assert max(kept) <= 6, kept  # before: the colour of all 9 skipped frames at once (10)
