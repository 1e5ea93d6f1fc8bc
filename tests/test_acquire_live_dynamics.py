"""The live path against the double's dynamics (tests/fake_realsense.py): a re-enumeration that
takes a while and throws from device creation and option calls meanwhile, several cameras, and
the recoveries of the warm-up and the calibration. Each test names what the device does."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import fake_realsense as frs
from test_acquire_live import camera, run_take

from depthstation.acquire.guided_capture import LiveState
from depthstation.core.device import CameraUnsuitable
from depthstation.core.protocol import Streams

PROTO_STREAMS = Streams(width=640, height=360, fps=30)


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """Inject a world with one D455 as `pyrealsense2`; `fake(**unit options)` builds it."""

    def make(**unit: Any) -> tuple[frs.FakeRealSense, frs.FakeUnit]:
        u = frs.FakeUnit(**unit)
        world = frs.FakeRealSense(u)
        monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)
        return world, u

    yield make


@pytest.mark.parametrize("fault", ["unplug", "stall"])
def test_a_reenumeration_that_throws_meanwhile_is_waited_out(fake: Any, tmp_path: Path, fault: str) -> None:
    """While the device comes back its interfaces enumerate one by one: creating it from the list
    and its option calls throw RuntimeError, and it leaves and arrives again twice. The take is
    redone after it settles; no RuntimeError leaves the capture (it ended the session as an
    internal error)."""
    world, unit = fake(enumerate_s=0.4, flaps=2)
    armed = [False]

    def hook(st: LiveState) -> None:
        if st.phase == "recording" and st.recorded == 3 and not armed[0]:
            armed[0] = True
            if fault == "unplug":
                unit.unplug(0.05)
            else:
                unit.stall()

    s, _, _ = run_take(world, unit, tmp_path, hook)
    assert [e["status"] for e in s.standpoints] == ["discarded", "complete"]
    names = world.names()
    assert "create_device_failed" in names  # the live path met the throwing creation
    assert names.count("added") >= 3  # and the extra arrivals
    assert s.data["capture"]["events"][-1]["event"] == "reconnected"


def test_device_creation_that_throws_is_a_camera_error(fake: Any) -> None:
    """A start while the device enumerates fails as a CameraError (retried by the capture), never
    a RuntimeError."""
    from depthstation.core.errors import CameraError

    world, unit = fake(enumerate_s=0.3)
    world._remove(unit)
    world._add(unit)
    cam = camera()
    with pytest.raises(CameraError):
        cam.start(PROTO_STREAMS)
    assert "create_device_failed" in world.names()
    time.sleep(0.35)
    cam.start(PROTO_STREAMS)
    cam.stop()


def test_several_cameras_without_a_serial_are_listed(monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = frs.FakeUnit(serial="111"), frs.FakeUnit(serial="222")
    world = frs.FakeRealSense(a, b)
    monkeypatch.setitem(sys.modules, "pyrealsense2", world.module)
    with pytest.raises(CameraUnsuitable, match=r"serials 111, 222.*live:SERIAL"):
        camera().start(PROTO_STREAMS)
    cam = camera(serial="222")
    cam.start(PROTO_STREAMS)
    assert b.streaming() and not a.streaming()
    cam.stop()
