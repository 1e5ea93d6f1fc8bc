"""Bringing a camera back after it stalled or dropped off: the one recovery the warm-up and the
guided capture share.

A stalled stream (no frames while the device stays listed) is reset where the camera can
(`hardware_reset`, Intel's remedy for a stall); then the protocol's streams are started again until
the camera answers or the time-out passes. A device still enumerating throws from its creation and
option calls: those failures are retried like any other. A camera back in an unsuitable state (on
USB 2) is said once and waited for.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

from depthstation.core.device import CameraStalled, CameraUnsuitable
from depthstation.core.errors import CameraError

RETRY_PAUSE_S = 0.5  # between two starts (the Viewer waits 600 ms after a stop and retries once)


def reconnect(camera: Any, start: Callable[[], Any], cause: BaseException | None, *, timeout_s: float,
              sleep: Callable[[float], None] = time.sleep, say: Callable[[str], None] | None = None) -> Any:
    """Stop; after a stall reset the device where it can; then `start()` until it answers (its
    value) or `timeout_s` passes (a CameraError naming the last failure)."""
    stalled = isinstance(cause, CameraStalled)
    if say is not None:
        say("camera stalled (no frames while connected): resetting it" if stalled
            else "camera disconnected: reconnect it (waiting)")
    with contextlib.suppress(CameraError, RuntimeError):
        camera.stop()
    reset = getattr(camera, "hardware_reset", None)
    if stalled and callable(reset):
        try:
            reset()
        except (CameraError, RuntimeError) as exc:  # a device call that threw while it re-enumerates
            if say is not None:
                say(f"{exc} (waiting)")
    t_end = time.monotonic() + timeout_s
    said = ""
    while True:
        try:
            return start()
        except (CameraError, RuntimeError) as exc:
            # RuntimeError: a device call the camera did not wrap (a device still enumerating
            # throws from its creation and option calls): retried like any other
            if isinstance(exc, CameraUnsuitable) and str(exc) != said and say is not None:
                said = str(exc)
                say(said)
            if time.monotonic() > t_end:
                raise CameraError(f"camera did not come back within {timeout_s:g} s: {exc}") from exc
            sleep(RETRY_PAUSE_S)
