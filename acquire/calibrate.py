"""On-device calibration (on-chip self-calibration, tare), each health value read on its own scale.

On-chip (Intel, librealsense `rs_device.h`): one health value, how far the current calibration is
from the optimal one: |h| in [0, 0.25) good, [0.25, 0.75) can be improved, [0.75, inf) requires
calibration; the Viewer recommends keeping the current table below 0.25.
Tare: (before, after), the relative depth error at the ground truth as a fraction (Z / GT - 1,
`d400-auto-calibration.cpp`), shown in % as the Viewer shows it. Intel gives no bands for tare;
applying is recommended when the error before is above the protocol's `tare_min_error` (our
choice) and the new table lowers it. The ground truth is the target's distance from the depth
origin: the operator measures from the front glass, and the model's offset is added.

A run leaves its new table active in the device's RAM (Intel's examples and Viewer): "no" puts
back the table that was active before; "yes" keeps it in RAM (a live camera sets it again after
every reset or replug) and, with `write`, burns it to flash. `session.json` says which.
"""

from __future__ import annotations

import base64
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from depthstation.core.device import (
    CalibratableCamera,
    CalibrationResult,
    CalibrationUnavailable,
    depth_origin_offset_m,
    device_model,
)
from depthstation.core.errors import CameraError, InputError
from depthstation.core.protocol import Calibration


class CalibrationFailed(CameraError):
    """The device ran a self-calibration and gave no table ("low fill factor", "failed to
    converge", "edges too close", a time-out): the scene or the aim, not the camera, is at fault."""


class CalibrationAborted(CameraError):
    """The operator ended the session at a failed calibration; `--resume` runs it again."""


UNATTENDED_RETRIES = 2  # --yes: a failed run is tried again this often, then skipped (recorded)
RETRY, SKIP, ABORT = "retry", "skip", "abort"
# what an operator can do about each verdict the firmware gives (d400-auto-calibration.cpp texts)
FAILURE_HINTS = (
    ("fill factor", "too few depth pixels: aim at a textured flat surface that fills the view, emitter on"),
    ("edges too close", "the target's edges are too close: fill the view with the flat target"),
    ("converge", "no solution: hold still and check the distance (tare: measure it again)"),
    ("time", "it ran out of time: hold still, better light, then retry"),
)


def failure_hint(message: str) -> str:
    """What to do about a failed self-calibration, from the firmware's words."""
    low = message.lower()
    return next((hint for key, hint in FAILURE_HINTS if key in low),
                "re-aim at the target and hold still, then retry")

GOOD, IMPROVABLE, REQUIRED = "good", "can be improved", "requires calibration"
TARE_SMALL, TARE_OFF, TARE_NOT_IMPROVED = "within tolerance", "off", "not improved"


@dataclass(frozen=True)
class HealthVerdict:
    health: float
    level: str
    meaning: str
    recommend_apply: bool


def health_verdict(health: float, threshold: float = 0.25) -> HealthVerdict:
    """What an on-chip health value means (Intel's bands) and whether to apply the new table."""
    h = abs(health)
    if h < 0.25:
        level, meaning = GOOD, "the current calibration is close to optimal; the new table changes little"
    elif h < 0.75:
        level, meaning = IMPROVABLE, "the new table improves depth noise or accuracy; worth applying"
    else:
        level, meaning = REQUIRED, "the current calibration is far off; apply the new table"
    return HealthVerdict(float(health), level, meaning, h >= threshold)


on_chip_verdict = health_verdict


@dataclass(frozen=True)
class TareVerdict:
    before: float  # relative depth error (fraction) at the ground truth with the current table
    after: float  # the same with the new table
    level: str
    meaning: str
    recommend_apply: bool


def tare_verdict(before: float, after: float, min_error: float = 0.002) -> TareVerdict:
    """What a tare result means: the depth error before and after, and whether to apply."""
    if abs(before) <= min_error:
        level, meaning, apply = TARE_SMALL, (f"the depth error is within {100 * min_error:.2f} %: "
                                             "keep the current table"), False
    elif abs(after) < abs(before):
        level, meaning, apply = TARE_OFF, "the new table lowers the depth error: apply it", True
    else:
        level, meaning, apply = TARE_NOT_IMPROVED, ("the new table does not lower the depth error: keep "
                                                    "the current one and check the ground truth"), False
    return TareVerdict(float(before), float(after), level, meaning, apply)


def _b64(table: bytes) -> str:
    return base64.b64encode(table).decode("ascii")


def calibration_step(camera: CalibratableCamera, result: CalibrationResult, cal: Calibration,
                     confirm: Callable[[str], bool], say: Callable[[str], None],
                     write: bool, current: bytes, unattended: bool = False) -> tuple[dict[str, Any], bytes]:
    """Show one result, ask, apply (or put `current` back) and return its session record and the
    table now active. `unattended` (--yes): a table that is not recommended is not applied, not
    asked for; a script's yes cannot mean "apply a table that makes the depth no better"."""
    if result.kind == "tare":
        before, after = result.health[0], result.health[1]
        tv = tare_verdict(before, after, cal.tare_min_error)
        say(f"tare: depth error at the ground truth {100 * before:+.3f} % before -> {100 * after:+.3f} % "
            f"after -> {tv.level}: {tv.meaning} (Intel gives no tare bands; ours: apply above "
            f"{100 * cal.tare_min_error:.2f} % when it improves)")
        recommend, levels = tv.recommend_apply, [tv.level]
        scale = "relative depth error at the ground truth (fraction): before, after"
        why_not = "not needed: the depth error is small or not improved"
    else:
        v = on_chip_verdict(result.health[0], cal.min_health)
        say(f"on-chip: health {v.health:+.3f} -> {v.level}: {v.meaning}")
        recommend, levels = v.recommend_apply, [v.level]
        scale = "Intel on-chip health: |h| < 0.25 good, < 0.75 can be improved, else requires calibration"
        why_not = "not needed: health is good"
    question = f"Apply the new {result.kind} table? " + ("(recommended)" if recommend else f"({why_not})")
    if unattended and not recommend:
        say(f"{question} no (--yes applies only a recommended table)")
        applied = False
    else:
        applied = bool(confirm(question))
    if applied:
        camera.set_calibration_table(result.table)
        if write:
            camera.write_calibration()
        active = result.table
        say(f"{result.kind}: new table applied" + (" and written to the device's flash" if write else
                                                   " in the device's RAM (set again after every reconnect)"))
    else:
        camera.set_calibration_table(current)  # the run left its table active: put the old one back
        active = current
        say(f"{result.kind}: kept the current table")
    record = {
        "kind": result.kind,
        "health": list(result.health),
        "health_scale": scale,
        "verdict": levels,
        "recommended": recommend,
        "applied": applied,
        "written": applied and write,
        "table_new_b64": _b64(result.table),
        "details": dict(result.details),
    }
    return record, active


def tare_ground_truth(camera: Any, distance_from_glass_m: float) -> tuple[float, dict[str, Any]]:
    """Depth-origin distance (m) for a target `distance_from_glass_m` from the front glass, and
    what went into it: the model's offset where Intel gives one, else none (said)."""
    info = camera.device_info() if callable(getattr(camera, "device_info", None)) else {}
    model = device_model(str(info.get("name", "")))
    offset = depth_origin_offset_m(model)
    gt = distance_from_glass_m + (offset or 0.0)
    return gt, {"distance_from_glass_m": distance_from_glass_m, "model": model,
                "depth_origin_behind_glass_mm": None if offset is None else round(offset * 1000.0, 3),
                "ground_truth_m": gt}


def _failed_step(kind: str, failures: list[str]) -> dict[str, Any]:
    """A run skipped after failing: nothing applied, each failure kept."""
    return {"kind": kind, "skipped": True, "applied": False, "written": False,
            "reason": f"failed {len(failures)} time(s), skipped: {failures[-1]}", "failures": failures}


def _skipped(reason: str, steps: list[dict[str, Any]]) -> dict[str, Any]:
    return {"skipped": True, "reason": reason, "steps": steps}


def attempt(kind: str, run: Callable[[], CalibrationResult], say: Callable[[str], None],
            choose: Callable[[str], str] | None, retries: int = UNATTENDED_RETRIES
            ) -> tuple[CalibrationResult | None, list[str]]:
    """Run one self-calibration; on a failure the operator retries (after re-aiming), skips or
    aborts (`choose(question)` -> 'retry' | 'skip' | 'abort'); without `choose` (--yes) it is
    retried `retries` times, then skipped. The result (None when skipped) and every failure."""
    failures: list[str] = []
    while True:
        try:
            return run(), failures
        except CalibrationFailed as exc:
            failures.append(str(exc))
            hint = failure_hint(str(exc))
            say(f"{kind} calibration failed ({exc}): {hint}")
            if choose is None:
                answer = RETRY if len(failures) <= retries else SKIP
                say(f"{kind}: {answer} (--yes: {retries} retries, then skip)")
            else:
                answer = choose(f"{kind} calibration failed: retry (re-aim first), skip it, or abort the "
                                "session?")
            if answer == ABORT:
                raise CalibrationAborted(f"{kind} calibration failed ({exc}) and the session was stopped: "
                                         f"{hint}; --resume runs the calibration again") from exc
            if answer == SKIP:
                return None, failures


def run_calibration(camera: Any, cal: Calibration, *, confirm: Callable[[str], bool],
                    say: Callable[[str], None] = print, write: bool = False, timeout_s: float = 30.0,
                    ask_distance: Callable[[str, float], float] | None = None,
                    unattended: bool = False, choose: Callable[[str], str] | None = None) -> dict[str, Any]:
    """The protocol's calibration steps in order (on-chip, then tare); the record for session.json.

    Cameras that cannot self-calibrate (playback, simulation without the feature) and cameras that
    cannot enter the calibration mode (USB 2) are recorded as skipped with the reason, so a session
    says what state its camera was in. `ask_distance(question, default)` lets the operator enter the
    tare target's measured distance from the front glass (default: the protocol's). `unattended`
    (--yes): only recommended tables are applied (`calibration_step`). A run that fails is retried,
    skipped or aborted (`attempt`; `choose` asks the operator, else --yes's policy); a skipped run
    is recorded with every failure.
    """
    if not isinstance(camera, CalibratableCamera):
        say("this camera cannot self-calibrate (recording or simulation): calibration skipped")
        return _skipped("camera has no on-device calibration", [])
    if cal.tare and cal.tare_distance_m is None:
        raise InputError(None, "'calibration.tare' needs 'calibration.tare_distance_m'")
    flash_before = camera.calibration_table()
    active_of = getattr(camera, "active_calibration_table", None)
    before = active_of() if callable(active_of) else flash_before
    active = before
    steps: list[dict[str, Any]] = []
    try:
        if cal.on_chip:
            say("on-chip calibration: point the camera at a textured flat surface about 0.5-1 m away "
                "and hold still")
            got, failed = attempt("on-chip", lambda: camera.run_on_chip_calibration(timeout_s), say, choose)
            if got is None:
                steps.append(_failed_step("on_chip", failed))
            else:
                step, active = calibration_step(camera, got, cal, confirm, say, write, active, unattended)
                steps.append({**step, "failures": failed} if failed else step)
        if cal.tare:
            assert cal.tare_distance_m is not None
            glass = cal.tare_distance_m
            if ask_distance is not None:
                glass = float(ask_distance("tare: distance from the camera's front glass to the flat target "
                                           "(m)", glass))
            gt, where = tare_ground_truth(camera, glass)
            offset = where["depth_origin_behind_glass_mm"]
            say(f"tare calibration: face a flat target squarely, filling the image centre, {glass:.3f} m "
                "from the camera's front glass; ground truth " + (
                    f"{1000 * gt:.2f} mm from the depth origin ({offset:g} mm behind the glass on a "
                    f"{where['model']})" if offset is not None else
                    f"{1000 * gt:.2f} mm (no depth-origin offset known for this model)"))
            got, failed = attempt("tare", lambda: camera.run_tare_calibration(gt, timeout_s), say, choose)
            if got is None:
                steps.append({**_failed_step("tare", failed), "details": where})
            else:
                res = CalibrationResult(got.kind, got.table, got.health, {**got.details, **where})
                step, active = calibration_step(camera, res, cal, confirm, say, write, active, unattended)
                steps.append({**step, "failures": failed} if failed else step)
    except CalibrationUnavailable as exc:
        say(str(exc))
        return {**_skipped(str(exc), steps), "table_before_b64": _b64(before),
                "table_after_b64": _b64(active)}
    written = any(s["written"] for s in steps)
    changed = active != before
    return {"skipped": False, "table_before_b64": _b64(before), "table_after_b64": _b64(active),
            "table_flash_b64": _b64(camera.calibration_table() if written else flash_before),
            "changed": changed,
            "applied_to": "flash" if written else ("ram" if active != flash_before else None),
            "reapplied_after_reconnect": bool(not written and active != flash_before
                                              and callable(getattr(camera, "hold_calibration", None))),
            "steps": steps}
