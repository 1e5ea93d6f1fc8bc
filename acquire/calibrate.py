"""On-device calibration (on-chip self-calibration, tare) with health values explained.

Intel's health check (librealsense `rs2_run_on_chip_calibration`): the absolute value says how far
the current calibration is from the optimal one: [0, 0.25) good, [0.25, 0.75) can be improved,
[0.75, inf) requires calibration. A new table is applied only after the operator confirms
(or `--yes`), and only to the device's dynamic area unless `write` asks for the EEPROM; the
tables before and after and the health values go into the session.
"""

from __future__ import annotations

import base64
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from depthstation.core.device import CalibratableCamera, CalibrationResult
from depthstation.core.errors import InputError
from depthstation.core.protocol import Calibration

GOOD, IMPROVABLE, REQUIRED = "good", "can be improved", "requires calibration"


@dataclass(frozen=True)
class HealthVerdict:
    health: float
    level: str
    meaning: str
    recommend_apply: bool


def health_verdict(health: float, threshold: float = 0.25) -> HealthVerdict:
    """What a health-check value means (Intel's bands) and whether to apply the new table."""
    h = abs(health)
    if h < 0.25:
        level, meaning = GOOD, "the current calibration is close to optimal; the new table changes little"
    elif h < 0.75:
        level, meaning = IMPROVABLE, "the new table improves depth noise or accuracy; worth applying"
    else:
        level, meaning = REQUIRED, "the current calibration is far off; apply the new table"
    return HealthVerdict(float(health), level, meaning, h >= threshold)


def _b64(table: bytes) -> str:
    return base64.b64encode(table).decode("ascii")


def calibration_step(camera: CalibratableCamera, result: CalibrationResult, threshold: float,
                     confirm: Callable[[str], bool], say: Callable[[str], None],
                     write: bool) -> dict[str, Any]:
    """Show one calibration result, ask, apply (or not) and return its session record."""
    verdicts = [health_verdict(h, threshold) for h in result.health]
    for i, v in enumerate(verdicts):
        label = "health" if i == 0 else f"health[{i}]"
        say(f"{result.kind}: {label} {v.health:+.3f} -> {v.level}: {v.meaning}")
    recommend = bool(verdicts and verdicts[0].recommend_apply)
    question = (f"Apply the new {result.kind} table? "
                + ("(recommended)" if recommend else "(not needed: health is good)"))
    applied = bool(confirm(question))
    if applied:
        camera.set_calibration_table(result.table)
        if write:
            camera.write_calibration()
        say(f"{result.kind}: new table applied" + (" and written to the device" if write else ""))
    else:
        say(f"{result.kind}: kept the current table")
    return {
        "kind": result.kind,
        "health": list(result.health),
        "verdict": [v.level for v in verdicts],
        "recommended": recommend,
        "applied": applied,
        "written": applied and write,
        "table_new_b64": _b64(result.table),
        "details": dict(result.details),
    }


def run_calibration(camera: Any, cal: Calibration, *, confirm: Callable[[str], bool],
                    say: Callable[[str], None] = print, write: bool = False,
                    timeout_s: float = 30.0) -> dict[str, Any]:
    """The protocol's calibration steps in order (on-chip, then tare); the record for session.json.

    Cameras that cannot self-calibrate (playback, simulation without the feature) are recorded as
    skipped with the reason, so a session says what state its camera was in.
    """
    if not isinstance(camera, CalibratableCamera):
        say("this camera cannot self-calibrate (recording or simulation): calibration skipped")
        return {"skipped": True, "reason": "camera has no on-device calibration", "steps": []}
    if cal.tare and cal.tare_distance_m is None:
        raise InputError(None, "'calibration.tare' needs 'calibration.tare_distance_m'")
    before = camera.calibration_table()
    steps: list[dict[str, Any]] = []
    if cal.on_chip:
        say("on-chip calibration: point the camera at a textured flat surface and hold still")
        res = camera.run_on_chip_calibration(timeout_s)
        steps.append(calibration_step(camera, res, cal.min_health, confirm, say, write))
    if cal.tare:
        assert cal.tare_distance_m is not None
        say(f"tare calibration: place the camera {cal.tare_distance_m:.3f} m from a flat target, facing it")
        res = camera.run_tare_calibration(cal.tare_distance_m, timeout_s)
        steps.append(calibration_step(camera, res, cal.min_health, confirm, say, write))
    after = camera.calibration_table()
    return {"skipped": False, "table_before_b64": _b64(before), "table_after_b64": _b64(after),
            "changed": before != after, "steps": steps}
