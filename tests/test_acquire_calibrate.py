"""Calibration flow: health bands (Intel) for on-chip, the relative depth error for tare, apply only
on confirmation (else the previous table is put back), tables recorded; live helpers."""

from __future__ import annotations

import base64

import pytest

from depthstation.acquire.calibrate import (
    GOOD,
    IMPROVABLE,
    REQUIRED,
    TARE_NOT_IMPROVED,
    TARE_OFF,
    TARE_SMALL,
    health_verdict,
    run_calibration,
    tare_verdict,
)
from depthstation.acquire.live_camera import LiveCamera, read_options, read_temperatures
from depthstation.core.device import CalibrationResult
from depthstation.core.errors import InputError
from depthstation.core.protocol import Calibration


class FakeDevice:
    """A device-side calibration engine: new tables differ from the current one by a suffix, and a
    run leaves its table active (as the device does)."""

    def __init__(self, health: float) -> None:
        self.table = b"factory"
        self.health = health
        self.written = False

    def calibration_table(self) -> bytes:
        return self.table

    def run_on_chip_calibration(self, timeout_s: float = 30.0) -> CalibrationResult:
        self.table += b"+occ"
        return CalibrationResult("on_chip", self.table, (self.health,))

    def run_tare_calibration(self, ground_truth_m: float, timeout_s: float = 30.0) -> CalibrationResult:
        self.table += b"+tare"
        return CalibrationResult("tare", self.table, (self.health, 0.0001),
                                 {"ground_truth_m": ground_truth_m})

    def set_calibration_table(self, table: bytes) -> None:
        self.table = table

    def write_calibration(self) -> None:
        self.written = True


@pytest.mark.parametrize(("h", "level", "apply"), [(0.1, GOOD, False), (-0.3, IMPROVABLE, True),
                                                   (0.74, IMPROVABLE, True), (1.2, REQUIRED, True)])
def test_health_bands(h: float, level: str, apply: bool) -> None:
    v = health_verdict(h)
    assert v.level == level and v.recommend_apply == apply


@pytest.mark.parametrize(("before", "after", "level", "apply"), [
    (0.001, 0.0001, TARE_SMALL, False), (-0.012, 0.001, TARE_OFF, True), (0.2, 0.0002, TARE_OFF, True),
    (0.01, 0.02, TARE_NOT_IMPROVED, False)])
def test_tare_verdict_on_the_relative_error(before: float, after: float, level: str, apply: bool) -> None:
    v = tare_verdict(before, after, min_error=0.002)
    assert v.level == level and v.recommend_apply == apply


def test_applies_only_after_confirmation() -> None:
    dev = FakeDevice(0.5)
    said: list[str] = []
    rec = run_calibration(dev, Calibration(on_chip=True, tare=False), confirm=lambda q: False,
                          say=said.append)
    assert dev.table == b"factory" and not rec["changed"] and not rec["steps"][0]["applied"]
    assert any("can be improved" in s for s in said)
    rec = run_calibration(dev, Calibration(on_chip=True, tare=True, tare_distance_m=1.0),
                          confirm=lambda q: True, say=said.append)
    assert dev.table == b"factory+occ+tare" and rec["changed"] and not dev.written
    assert base64.b64decode(rec["table_before_b64"]) == b"factory"
    assert base64.b64decode(rec["table_after_b64"]) == b"factory+occ+tare"
    assert [s["kind"] for s in rec["steps"]] == ["on_chip", "tare"]


def test_tare_needs_distance_and_playback_is_skipped() -> None:
    with pytest.raises(InputError, match="tare_distance_m"):
        run_calibration(FakeDevice(0.1), Calibration(tare=True), confirm=lambda q: True, say=lambda s: None)
    rec = run_calibration(object(), Calibration(), confirm=lambda q: True, say=lambda s: None)
    assert rec["skipped"]


def test_live_option_and_temperature_readers_on_a_software_sensor() -> None:
    rs = pytest.importorskip("pyrealsense2")
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    sensor.add_read_only_option(rs.option.asic_temperature, 41.5)
    sensor.add_read_only_option(rs.option.projector_temperature, 44.0)
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    assert read_temperatures(sensor) == {"asic": 41.5, "projector": 44.0}
    opts = read_options(sensor)
    assert opts["depth_units"] == pytest.approx(0.001) and opts["asic_temperature"] == pytest.approx(41.5)
    bare = dev.add_sensor("RGB Camera")
    assert read_temperatures(bare) == {}  # the D400 has no temperature metadata to fall back on


def test_live_camera_imports_without_device() -> None:
    cam = LiveCamera(serial="000000000000")
    assert cam.temperatures() == {} and cam.options() == {}


@pytest.mark.hardware
def test_live_d455_streams_and_reports() -> None:
    from depthstation.core.protocol import Streams

    cam = LiveCamera()
    info = cam.start(Streams(width=640, height=480, fps=30))
    try:
        fs = cam.wait_for_frames(5.0)
        assert fs.depth is not None and fs.depth.shape == (480, 640)
        assert 0.0001 <= info.depth_units_m <= 0.01
        assert "serial" in cam.device_info()
        assert cam.options()
    finally:
        cam.stop()


@pytest.mark.parametrize(("health", "applied"), [(0.1, False), (0.5, True)])
def test_unattended_yes_applies_only_a_recommended_table(health: float, applied: bool) -> None:
    """--yes answers the questions a script cannot, but not with "apply a table that is not needed":
    good health keeps the current table; an improvable one is applied."""
    dev = FakeDevice(health)
    said: list[str] = []
    rec = run_calibration(dev, Calibration(on_chip=True), confirm=lambda q: True, say=said.append,
                          unattended=True)
    assert rec["steps"][0]["applied"] is applied and rec["steps"][0]["recommended"] is applied
    assert dev.table == (b"factory+occ" if applied else b"factory")
    assert any("--yes applies only a recommended table" in s for s in said) is not applied
