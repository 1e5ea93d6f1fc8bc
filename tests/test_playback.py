"""PlaybackCamera: a recording behaves like a live camera (same pipeline, frames, geometry, options)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from depthstation.acquire.playback_camera import PlaybackCamera
from depthstation.core.capture.rs_writer import write_realsense_recording
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.device import Camera
from depthstation.core.errors import CameraError, InputError
from depthstation.core.protocol import Streams


def test_playback_of_recorded_db3_delivers_every_frame(tmp_path: Path) -> None:
    info = sample_info(64, 48)
    frames = list(sample_frames(info, 5, seed=3))
    path = tmp_path / "rec.db3"
    write_realsense_recording(path, info, frames)
    cam = PlaybackCamera(path)
    assert isinstance(cam, Camera)
    got_info = cam.start(Streams(width=64, height=48))
    try:
        assert got_info.depth_units_m == pytest.approx(0.001, rel=1e-6)
        assert got_info.baseline_m == pytest.approx(0.095, rel=1e-6)
        assert got_info.depth_intrinsics.fx == pytest.approx(info.depth_intrinsics.fx, rel=1e-6)
        assert got_info.color_intrinsics is not None
        assert got_info.color_intrinsics.model == "inverse_brown_conrady"
        np.testing.assert_allclose(got_info.depth_to_color.matrix, info.depth_to_color.matrix, atol=1e-6)
        assert cam.device_info()["serial_number"] == "000000000001"
        assert "depth_units" in cam.options()
        got = []
        with pytest.raises(EOFError):
            for _ in range(20):
                got.append(cam.wait_for_frames(timeout_s=1.0))
    finally:
        cam.stop()
    assert [f.index for f in got] == [f.index for f in frames]
    for a, b in zip(frames, got, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
        assert abs(b.timestamp_ns - a.timestamp_ns) < 1000
    assert any(
        np.array_equal(np.asarray(b.color), np.asarray(a.color)) for a, b in zip(frames, got, strict=True)
    )


def test_playback_real_bag(d435_bag: Path) -> None:
    with PlaybackCamera(d435_bag) as cam:
        info = cam.start(Streams(width=640, height=480, fps=6))
        assert info.depth_intrinsics.fx == pytest.approx(390.43, abs=0.01)
        assert info.baseline_m == pytest.approx(0.05017, abs=1e-5)
        assert cam.temperatures()["asic"] == pytest.approx(29.0)
        fs = cam.wait_for_frames(2.0)
        assert fs.depth is not None and fs.depth.shape == (480, 640)


def test_playback_refuses_non_recordings(tmp_path: Path) -> None:
    with pytest.raises(InputError):
        PlaybackCamera(tmp_path / "missing.db3")
    bad = tmp_path / "bad.db3"
    bad.write_bytes(b"nothing")
    cam = PlaybackCamera(bad)
    with pytest.raises(InputError):
        cam.start(None)


class _SilentPipe:
    """A pipeline that never delivers a frame (librealsense's timeout each time)."""

    calls = 0

    def wait_for_frames(self, timeout_ms: int) -> None:
        self.calls += 1
        raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")

    def stop(self) -> None:
        return None


@pytest.mark.parametrize(("status", "expected"), [("stopped", EOFError), ("playing", CameraError)])
def test_a_timeout_is_the_end_only_when_the_playback_has_stopped(
        d435_bag: Path, monkeypatch: pytest.MonkeyPatch, status: str, expected: type[Exception]) -> None:
    """A fresh playback on a loaded machine missed a 2 s timeout with frames still to come; that
    must not read as the end of the recording (a capture cut short without a word)."""
    import pyrealsense2 as rs

    from depthstation.acquire import playback_camera

    cam = PlaybackCamera(d435_bag)
    cam.start(Streams(width=640, height=480, fps=6))
    real = cam._pipe
    try:
        pipe = _SilentPipe()
        cam._pipe = pipe
        monkeypatch.setattr(cam, "_playback_status", lambda: getattr(rs.playback_status, status))
        with pytest.raises(expected):
            cam.wait_for_frames(0.01)
        assert pipe.calls == (1 if expected is EOFError else playback_camera.LATE_RETRIES + 1)
    finally:
        cam._pipe = real
        cam.stop()
