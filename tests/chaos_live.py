"""Guided sessions through the device double with faults drawn at random: the harness of
tests/test_acquire_chaos.py and benchmarks/chaos_sessions.py.

One session: `depthstation acquire session --camera live --yes` (in-process, the double injected
as pyrealsense2) with a seed's faults: stalls, unplugs and re-plugs (the old pipeline resuming or
not) at any frame of any phase, device creation throwing during each re-enumeration, OCC/tare
verdicts, a slow consumer, a full disk. It must end complete, or with a one-line reason after
which `--resume` (faults gone) completes it; no finished standpoint may change or vanish, and each
take's frame numbers must add up (recorded frames + device losses + host drops = the span).
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import itertools

import fake_realsense as frs
from full_disk import disk_full_after
from test_acquire_live import board_scene

from depthstation.acquire.live_camera import LiveCamera
from depthstation.app.cli import run_cli
from depthstation.core.board import Board

PROTOCOL = ('name = "chaos"\n[board]\ntype = "checkerboard"\nsquares_x = 7\nsquares_y = 5\n'
            'square_length_m = 0.095\n[streams]\nwidth = 640\nheight = 360\nfps = 30\n'
            '[plan]\nframes_per_standpoint = 6\nstart_distance_m = 1.0\nstep_m = 0.2\n'
            'max_distance_m = 1.0\ninclinations_deg = [0.0, 1.0]\n[tolerances]\nstill_seconds = 0.2\n'
            'inclination_deg = 3.0\n[warmup]\nmin_minutes = 0.005\nmax_minutes = 0.01\n'
            'window_minutes = 0.005\n[calibration]\non_chip = true\ntare = true\ntare_distance_m = 1.0\n'
            '[device]\nmodel = "D455"\n')
# the live camera's recovery waits scaled to the double's (a reset: gone in 0.05 s, back in 0.2 s)
FAST = {"removal_timeout_s": 2.0, "enumeration_timeout_s": 4.0, "quiet_s": 0.05, "poll_s": 0.01,
        "stop_deadline_s": 0.2, "first_frame_timeout_s": 2.0}
FRAME_TIMEOUT_S = 0.4  # a stall is noticed after this (the station's 5 s, scaled)
FRAME_FAULTS = ("stall", "unplug", "unplug_resume", "drop", "slow")


@dataclass
class Chaos:
    """One seed's faults."""

    seed: int
    frame_faults: dict[int, tuple[str, float]] = field(default_factory=dict)  # fetch number -> fault
    verdicts: list[str] = field(default_factory=list)
    enumerate_s: float = 0.0
    flaps: int = 0
    disk_budget: int | None = None
    calibration_unplug: int | None = None  # unplugged in the n-th switch into the calibration mode

    @classmethod
    def draw(cls, seed: int) -> Chaos:
        rng = np.random.default_rng(seed)
        c = cls(seed)
        for _ in range(int(rng.integers(0, 4))):
            at = int(rng.integers(1, 36))  # fetches: warm-up (~8), guidance and recording (~26)
            kind = str(rng.choice(FRAME_FAULTS))
            c.frame_faults[at] = (kind, float(rng.uniform(0.03, 0.3)))
        if rng.random() < 0.5:
            c.verdicts = [str(rng.choice(["ok", "ok", "fill", "edges", "converge", "timeout"]))
                          for _ in range(int(rng.integers(1, 6)))]
        if rng.random() < 0.5:
            c.enumerate_s, c.flaps = float(rng.choice([0.1, 0.3])), int(rng.integers(0, 3))
        if rng.random() < 0.1:
            c.disk_budget = int(rng.integers(5_000, 400_000))
        if rng.random() < 0.15:
            c.calibration_unplug = int(rng.integers(1, 3))
        return c

    def count(self) -> int:
        """Stalls, unplugs, drops and slow frames drawn (at a fetch, or in the calibration mode)."""
        return len(self.frame_faults) + (self.calibration_unplug is not None)

    def describe(self) -> str:
        parts = [f"{k}@{a}" for a, (k, _) in sorted(self.frame_faults.items())]
        parts += [f"verdicts={','.join(self.verdicts)}"] * bool(self.verdicts)
        parts += [f"enumerate={self.enumerate_s:g}s/flaps={self.flaps}"] * bool(self.enumerate_s)
        parts += [f"disk_full@{self.disk_budget}B"] * (self.disk_budget is not None)
        parts += [f"unplug_in_calibration@{self.calibration_unplug}"] * (self.calibration_unplug is not None)
        return " ".join(parts) or "no faults"


@dataclass
class Outcome:
    seed: int
    chaos: str
    first_code: int
    reason: str | None  # the one line the first run ended with, when it failed
    resumed: bool
    problems: list[str]
    seconds: float = 0.0
    faults_hit: int = 0
    fetches: int = 0
    faults_drawn: int = 0
    verdicts_failed: int = 0  # self-calibrations the double failed
    creation_errors: int = 0  # devices whose creation threw during a re-enumeration


def _acquire(args: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = run_cli(["acquire", *args])
    return code, err.getvalue()


def run_session(seed: int, root: Path) -> Outcome:
    """One chaotic session and, when it stopped, its resume; what went wrong in `problems`."""
    import time

    t0 = time.monotonic()
    chaos = Chaos.draw(seed)
    unit = frs.FakeUnit(scene=board_scene(Board(), 1.0), enumerate_s=chaos.enumerate_s, flaps=chaos.flaps,
                        reset_delays_s=(0.05, 0.2), depth_bias=0.01, on_chip_health=0.4)
    unit.verdicts = list(chaos.verdicts)
    world = frs.FakeRealSense(unit)
    proto = root / "chaos.toml"
    proto.write_text(PROTOCOL)
    sess = root / "s"
    args = ["session", "--camera", "live", "--protocol", str(proto), "--session", str(sess), "--yes",
            "--interval", "0.1", "--max-guidance", "30"]
    calls = [0]
    hit = [0]
    active = [True]
    real_init, real_wait = LiveCamera.__init__, LiveCamera.wait_for_frames
    real_enter = LiveCamera._enter_calibration_mode
    entered = [0]

    def enter(self: LiveCamera, dev: Any) -> None:
        real_enter(self, dev)
        entered[0] += 1
        if active[0] and entered[0] == chaos.calibration_unplug:
            hit[0] += 1
            unit.unplug(0.1)

    def init(self: LiveCamera, *a: Any, **kw: Any) -> None:
        real_init(self, *a, **{**FAST, **kw})

    def wait(self: LiveCamera, timeout_s: float = 5.0) -> Any:
        calls[0] += 1
        fault = chaos.frame_faults.get(calls[0]) if active[0] else None
        if fault is not None:
            hit[0] += 1
            kind, x = fault
            if kind == "stall":
                unit.stall()
            elif kind == "unplug":
                unit.unplug(x)
            elif kind == "unplug_resume":
                unit.unplug(x, resume=True)
            elif kind == "drop":
                unit.inject(drop={"depth": 1 + int(10 * x), "color": int(10 * x)})
            elif kind == "slow":
                time.sleep(x)
        if active[0] and any(k == "slow" for k, _ in chaos.frame_faults.values()):
            time.sleep(0.03)  # a consumer about a frame period slow on every frame
        return real_wait(self, min(timeout_s, FRAME_TIMEOUT_S))

    problems: list[str] = []
    reason: str | None = None
    resumed = False
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "pyrealsense2", world.module)
        mp.setattr(LiveCamera, "__init__", init)
        mp.setattr(LiveCamera, "wait_for_frames", wait)
        mp.setattr(LiveCamera, "_enter_calibration_mode", enter)
        try:
            with contextlib.ExitStack() as stack:
                if chaos.disk_budget is not None:
                    stack.enter_context(disk_full_after(mp, sess, chaos.disk_budget))
                code, err = _acquire(args)
        except Exception as exc:  # an internal error: what must never happen
            code, err = -1, f"internal error: {type(exc).__name__}: {exc}"
        first_code = code
        if code != 0:
            lines = [ln for ln in err.splitlines() if ln.startswith("depthstation: error:")]
            reason = lines[-1] if lines else err.strip().splitlines()[-1] if err.strip() else "(silent)"
            if code not in (1, 2) or not lines:
                problems.append(f"ended with code {code} without a one-line reason: {reason}")
            done_before = _complete_files(sess)
            active[0] = False
            unit.verdicts = []
            world.units[0].stalled = False
            time.sleep(0.3)  # a replug under way finishes
            resumed = True
            try:
                code, err = _acquire([*args, "--resume"])
            except Exception as exc:
                code, err = -1, f"internal error: {type(exc).__name__}: {exc}"
            if code != 0:
                problems.append(f"--resume failed (code {code}): {err.strip().splitlines()[-1:]}")
            for name, stamp in done_before.items():
                if _complete_files(sess).get(name) != stamp:
                    problems.append(f"{name}, complete before the resume, changed or vanished")
    problems += check_session(sess)
    return Outcome(seed, chaos.describe(), first_code, reason, resumed, problems, time.monotonic() - t0,
                   hit[0], calls[0], chaos.count(),
                   sum(n.endswith("_calibration_failed") for n in world.names()),
                   world.names().count("create_device_failed"))


def _complete_files(sess: Path) -> dict[str, tuple[int, int]]:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in sess.glob("standpoint_*.mcap")}


def check_session(sess: Path) -> list[str]:
    """What a finished session must hold: every standpoint complete with its frames, numbers that
    add up, a warm-up and a calibration record that say what happened."""
    from depthstation.core.capture.registry import open_recording

    out: list[str] = []
    path = sess / "session.json"
    if not path.is_file():
        return ["no session.json"]
    data = json.loads(path.read_text())
    complete = [e for e in data.get("standpoints", []) if e.get("status") == "complete"]
    names = sorted({e["name"] for e in complete})
    if names != ["standpoint_01", "standpoint_02"]:
        out.append(f"complete standpoints {names}")
    warm = data.get("warmup")
    if not isinstance(warm, dict) or not warm.get("done"):
        out.append("no finished warm-up record")
    cal = data.get("calibration")
    if not isinstance(cal, dict):
        out.append("no calibration record")
    else:
        for step in cal.get("steps", []):
            if step.get("skipped") and not step.get("reason"):
                out.append(f"calibration step {step.get('kind')} skipped without a reason")
    for e in complete:
        rec = open_recording(sess / e["file"])
        frames = list(rec.frames())
        if len(frames) != 6:
            out.append(f"{e['file']}: {len(frames)} frames, not 6")
            continue
        idx = [f.index for f in frames]
        if any(b <= a for a, b in itertools.pairwise(idx)):
            out.append(f"{e['file']}: frame numbers not increasing {idx}")
        fr = rec.metadata["standpoint"]["frames"]
        lost, host = fr.get("device_frames_lost"), fr.get("host_frames_dropped")
        if lost is not None and host is not None:
            span = idx[-1] - idx[0] + 1 - len(idx)
            if span != lost["depth"] + host["depth"]:
                out.append(f"{e['file']}: {span} depth numbers missing, recorded {lost['depth']} lost on the "
                           f"device + {host['depth']} dropped on the host")
    return out
