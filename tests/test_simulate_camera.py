"""The simulated camera: protocols, warm-up, thermal drift, calibration, faults and reconnect."""

from __future__ import annotations

import numpy as np
import pytest

from depthstation.core.device import CalibratableCamera, Camera
from depthstation.core.errors import CameraDisconnected, CameraError
from depthstation.core.protocol import Streams
from depthstation.simulate.effects.base import PixelContext
from depthstation.simulate.poses import standpoint_pose
from depthstation.simulate.simulated_camera import SimulatedCamera

STREAMS = Streams(width=320, height=180, fps=30)


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _centre_depth(cam: SimulatedCamera, n: int = 4) -> float:
    """Mean depth over the board's central patch, averaged over n frames (m)."""
    vals = []
    for _ in range(n):
        fs = cam.wait_for_frames()
        d = fs.depth_m(0.001)
        vals.append(np.nanmean(d[80:100, 145:175]))
    return float(np.mean(vals))


def test_protocols_and_info() -> None:
    cam = SimulatedCamera("d455-ideal")
    assert isinstance(cam, Camera) and isinstance(cam, CalibratableCamera)
    with pytest.raises(CameraError):
        cam.wait_for_frames()
    info = cam.start(STREAMS)
    assert info.depth_intrinsics.width == 320 and info.baseline_m == pytest.approx(0.095)
    fs = cam.wait_for_frames()
    assert fs.depth is not None and fs.depth.shape == (180, 320) and fs.color is not None
    assert cam.device_info()["serial_number"] and cam.options()["depth_units"] == 0.001


def test_warm_up_follows_first_order_model_on_accelerated_clock() -> None:
    clock = FakeClock()
    cam = SimulatedCamera("d455-ideal", clock=clock, clock_scale=60.0)  # one clock second = one device minute
    cam.start(STREAMS)
    temps = []
    for minute in (0, 6, 12, 24, 120):
        clock.t = float(minute)
        temps.append(cam.temperatures()["asic"])
    assert temps[0] == pytest.approx(25.0, abs=0.01)
    assert temps[2] == pytest.approx(40.0 - 15.0 * np.exp(-1.0), abs=0.01)  # one time constant (12 min)
    assert all(np.diff(temps) > 0) and temps[-1] == pytest.approx(40.0, abs=0.02)


def test_thermal_drift_and_tare() -> None:
    clock = FakeClock()
    pose = standpoint_pose(SimulatedCamera("d455-ideal").board, 1.5, 0.0)
    cam = SimulatedCamera("d455-ideal", clock=clock, pose=pose, seed=3)
    info = cam.start(STREAMS)
    fb = info.depth_intrinsics.fx * 0.095
    cold = _centre_depth(cam)
    clock.t = 10 * cam.tau_s  # warm
    warm = _centre_depth(cam)
    model = cam.effective_model()

    def predicted(temp: float) -> float:
        ctx = PixelContext(z_m=1.5, temperature_c=temp, fx=info.depth_intrinsics.fx, baseline_m=0.095)
        return float(1.5 + sum(e.bias_m(ctx) for e in model.effects if e.name in (
            "thermal_drift", "disparity_offset")))

    se = 1.5**2 * 0.08 / fb / np.sqrt(4 * 600) * 3 + 0.0007  # noise of the mean + quantisation
    assert cold - warm == pytest.approx(predicted(25.0) - predicted(40.0), abs=2 * se)
    assert warm == pytest.approx(predicted(40.0), abs=2 * se)
    # tare at 1.5 m takes most of the disparity offset away
    res = cam.run_tare_calibration(1.5)
    assert abs(res.health[1]) < 0.3 * abs(res.health[0])
    cam.set_calibration_table(res.table)
    after = _centre_depth(cam)
    assert abs(after - 1.5) < 0.4 * abs(warm - 1.5)


def test_on_chip_health_and_apply() -> None:
    cam = SimulatedCamera("d455-ideal")
    with pytest.raises(CameraError):
        cam.run_on_chip_calibration()
    cam.start(STREAMS)
    before = cam.calibration_table()
    res = cam.run_on_chip_calibration()
    assert 0.25 <= res.health[0] < 0.75  # "can be improved", like a unit off the shelf
    assert cam.calibration_table() == before  # not applied until asked
    cam.set_calibration_table(res.table)
    assert cam.on_chip_health() < 0.25 and cam.calibration_table() != before
    cam.write_calibration()
    assert cam.written_table == cam.calibration_table()


def test_disconnect_and_reconnect() -> None:
    cam = SimulatedCamera("d455-ideal", disconnect_after_frames=2, failed_reconnects=1)
    cam.start(STREAMS)
    first = [cam.wait_for_frames().index for _ in range(2)]
    with pytest.raises(CameraDisconnected):
        cam.wait_for_frames()
    with pytest.raises(CameraDisconnected):
        cam.wait_for_frames()
    cam.stop()
    with pytest.raises(CameraError):
        cam.start(STREAMS)  # still unplugged once
    cam.start(STREAMS)
    nxt = cam.wait_for_frames()
    assert first == [0, 1] and nxt.index == 2


def test_pose_provider_gets_device_time() -> None:
    seen: list[float] = []
    board = SimulatedCamera("d455-ideal").board

    def provider(t: float) -> np.ndarray:
        seen.append(t)
        return standpoint_pose(board, 1.0 + 0.5 * t, 0.0)

    cam = SimulatedCamera("d455-ideal", pose_provider=provider)
    cam.start(STREAMS)
    d = [_centre_depth(cam, 1) for _ in range(3)]
    np.testing.assert_allclose(np.diff(seen), 1 / 30, atol=1e-9)
    assert d[0] < d[1] < d[2]


def test_real_time_pacing() -> None:
    import time

    cam = SimulatedCamera("d455-ideal", real_time=True, clock_scale=2.0)
    cam.start(Streams(width=256, height=144, fps=30, color=False))
    t0 = time.monotonic()
    for _ in range(5):
        cam.wait_for_frames()
    assert time.monotonic() - t0 >= 4 / 60 - 0.005  # 30 fps at twice the speed
