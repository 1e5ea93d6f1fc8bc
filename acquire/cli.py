"""`depthstation acquire`: warm-up, on-device calibration and guided capture into a session.

Thin commands: parse, open the camera and the session, call the loops in `acquire.*`, print.
Every command takes `--camera live|PATH|sim[:MODEL]`, `--protocol`, `--session DIR`, `--resume`,
`--yes` and the rerun options; heavy imports stay inside the functions.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

app = typer.Typer(no_args_is_help=True, help="Warm-up, on-device calibration and guided capture.")

CameraOpt = typer.Option("sim", "--camera", help="live, live:SERIAL, a .db3/.bag recording, or sim[:MODEL]")
ProtocolOpt = typer.Option("checkerboard-d455", "--protocol",
                           help="protocol name in protocols/ or a TOML path")
SessionOpt = typer.Option(..., "--session", help="session directory (created; or continued with --resume)")
ResumeOpt = typer.Option(False, "--resume", help="continue an interrupted session")
YesOpt = typer.Option(False, "--yes", "-y", help="answer yes to every question (scripts)")
RrdOpt = typer.Option(None, "--rrd", help="write the live view to this .rrd file")
SpawnOpt = typer.Option(False, "--spawn", help="open a rerun viewer")
ServeOpt = typer.Option(False, "--serve", help="serve a local rerun web viewer")
SeedOpt = typer.Option(0, "--seed", help="seed of the simulated camera and operator")
RealTimeOpt = typer.Option(False, "--real-time",
                           help="pace a simulated camera or a recording at its frame rate")


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    """A stored protocol without its unset (null) keys, which the TOML form leaves out."""
    return {k: _drop_none(v) if isinstance(v, dict) else v for k, v in d.items() if v is not None}


class Station:
    """The objects one command works on: protocol, camera spec, camera, session."""

    def __init__(self, camera: str, protocol: str, session: Path, resume: bool, seed: int,
                 real_time: bool) -> None:
        from acquire.select import open_camera, parse_camera
        from depthstation.capture.session import SESSION_FILE, Session
        from depthstation.errors import InputError
        from depthstation.protocol import load_protocol, protocol_from_dict

        self.spec = parse_camera(camera)
        if resume:
            self.session = Session.open(session)
            stored = self.session.data.get("protocol")
            self.protocol = (protocol_from_dict(_drop_none(stored), session / SESSION_FILE)
                             if isinstance(stored, dict) else load_protocol(protocol))
        else:
            if (session / SESSION_FILE).exists():
                raise InputError(session, "holds a session already: add --resume to continue it")
            self.protocol = load_protocol(protocol)
            self.session = Session.create(session, protocol=self.protocol,
                                          camera=self.spec.describe())
        self.operator: Any = None
        options: dict[str, Any] = {}
        if self.spec.kind == "sim":
            options = {"seed": seed, "real_time": real_time}
        self.camera = open_camera(self.spec, **options)
        if self.spec.kind == "file" and real_time:
            self.camera.real_time = True
        self.seed = seed

    def attach_operator(self) -> Any:
        """With a simulated camera nobody holds it: a simulated operator follows the guidance."""
        if self.spec.kind != "sim":
            return None
        from simulate.operator import SimulatedOperator, Stance

        op = SimulatedOperator(self.protocol.board, Stance(range_m=self.protocol.plan.start_distance_m + 0.3,
                                                           azimuth_deg=-4.0, yaw_deg=3.0), seed=self.seed)
        fps = float(self.protocol.streams.fps)
        camera = self.camera
        camera.set_pose(op.pose(0.0))

        def on_guidance(g: Any, fs: Any, t_s: float) -> None:
            op.step(g, t_s)
            camera.set_pose(op.pose(t_s + 1.0 / fps))

        self.operator = op
        return on_guidance


def _say(text: str) -> None:
    from depthstation.progress import stderr_console

    stderr_console.print(text)


def _confirm(yes: bool) -> Any:
    def ask(question: str) -> bool:
        if yes:
            _say(f"{question} yes (--yes)")
            return True
        return typer.confirm(question, default=False, err=True)
    return ask


def do_warmup(st: Station, interval_s: float, accelerate: float, target: Any) -> dict[str, Any]:
    """Stream until the protocol's warm-up rule holds; the curve goes into the session and rerun."""
    import time
    from collections.abc import Callable

    from acquire.warmup import WarmupDecision, WarmupSample, run_warmup
    from depthstation.progress import progress
    from depthstation.viz import recording

    rule = st.protocol.warmup
    info = st.camera.start(st.protocol.streams)
    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    if accelerate > 1.0:
        # An accelerated, simulated clock: device time advances by exactly what the loop sleeps,
        # and the loop sleeps that much / `accelerate` of wall time. The wall time spent fetching
        # a frame does not count, so the warm-up curve is sampled every interval whatever the load
        # of the machine (a wall-clock multiple would turn 0.3 s of rendering into 2 min).
        virtual = [0.0]

        def fast_clock() -> float:
            return virtual[0]

        def fast_sleep(s: float) -> None:
            virtual[0] += s
            time.sleep(s / accelerate)
        clock, sleep = fast_clock, fast_sleep
        if hasattr(st.camera, "set_clock"):
            st.camera.set_clock(clock)
    try:
        with recording("depthstation-warmup", target, description="Warm-up: device temperatures "
                       "(degrees C) and the centre depth (m) over time (s).") as rec, \
                progress() as bar:
            task = bar.add_task("warm-up", total=rule.max_minutes * 60.0, status="")
            said_no_temp = [False]

            def on_sample(s: WarmupSample, d: WarmupDecision) -> None:
                if not d.has_temperature and not said_no_temp[0]:
                    said_no_temp[0] = True
                    _say("this camera reports no temperature: warm-up falls back to the minimum time")
                temp = s.temperature_c
                slope = "" if d.slope_c_per_min is None else f" slope {d.slope_c_per_min:+.3f} °C/min"
                bar.update(task, completed=s.t_s,
                           status=("" if temp is None else f"{temp:.1f} °C") + slope + f"  {d.reason}")
                if rec is not None:
                    import rerun as rr

                    rec.set_time("warmup_s", duration=s.t_s)
                    for k, v in s.temperatures_c.items():
                        rec.log(f"warmup/temperature_c/{k}", rr.Scalars([v]))
                    if s.depth_m is not None:
                        rec.log("warmup/centre_depth_m", rr.Scalars([s.depth_m]))

            result = run_warmup(st.camera, rule, info.depth_units_m, interval_s=interval_s, clock=clock,
                                sleep=sleep, on_sample=on_sample)
    finally:
        st.camera.stop()
        if accelerate > 1.0 and hasattr(st.camera, "set_clock"):
            st.camera.set_clock(None)  # back to frame time for what follows
    summary = result.summary()
    summary["interval_s"] = interval_s
    summary["accelerated"] = accelerate > 1.0
    st.session.set("warmup", summary)
    _say(f"warm-up done: {summary['reason']}")
    return summary


def do_calibrate(st: Station, yes: bool, write: bool) -> dict[str, Any]:
    from acquire.calibrate import run_calibration

    st.camera.start(st.protocol.streams)
    try:
        record = run_calibration(st.camera, st.protocol.calibration, confirm=_confirm(yes), say=_say,
                                 write=write)
    finally:
        st.camera.stop()
    st.session.set("calibration", record)
    return record


def do_capture(st: Station, target: Any, max_guidance_s: float | None) -> list[Any]:
    """The guided loop with the panel and rerun; a recording's end stops it cleanly."""
    import sys

    from acquire.capture import MOVED_MESSAGE, CaptureInterrupted, GuidedCapture, LiveState
    from acquire.views import BOARD_HELP, RerunView, TerminalPanel, blueprint
    from depthstation.viz import recording

    on_guidance = st.attach_operator()
    outcomes: list[Any] = []
    with recording("depthstation-acquire", target, blueprint(), description=BOARD_HELP) as rec:
        views: list[Any] = []
        panel = TerminalPanel() if sys.stderr.isatty() else None
        if panel is not None:
            views.append(panel)
        rerun_view: list[RerunView] = []

        def on_state(state: LiveState) -> None:
            if rec is not None and cap.info is not None:
                if not rerun_view:
                    rerun_view.append(RerunView(rec, cap.info.depth_units_m))
                rerun_view[0](state)
            for v in views:
                v(state)
            if panel is None and state.phase == "done":
                _say(f"{state.standpoint.name}: recorded {state.recorded} frames")
            if panel is None and state.message == MOVED_MESSAGE:
                _say(f"{state.standpoint.name}: {MOVED_MESSAGE}")

        cap = GuidedCapture(st.camera, st.protocol, st.session, on_guidance=on_guidance, on_state=on_state,
                            max_guidance_s=max_guidance_s)
        try:
            if panel is not None:
                panel.__enter__()
            outcomes = cap.run()
        except EOFError:
            _say("the recording ended: the standpoints done so far are in the session; "
                 "the rest stay open for --resume with another recording or a camera")
        except KeyboardInterrupt as exc:
            open_ = [e["name"] for e in st.session.standpoints if e.get("status") == "partial"]
            msg = (f"interrupted: finished standpoints are safe in {st.session.dir}"
                   + (f"; {', '.join(open_)} kept as partial" if open_ else "")
                   + "; --resume continues")
            raise CaptureInterrupted(msg) from exc
        finally:
            if panel is not None:
                panel.__exit__(None, None, None)
            if cap.events or cap.skipped:
                st.session.set("capture", {"skipped": dict(cap.skipped), "events": list(cap.events)})
    done = [e["name"] for e in st.session.standpoints if e.get("status") == "complete"]
    plan = [sp.name for sp in st.protocol.plan.standpoints()]
    open_ = [n for n in plan if n not in done and n not in cap.skipped]
    _say(f"session {st.session.dir}: {len(done)} standpoints complete, {len(cap.skipped)} skipped "
         f"(end of range), {len(open_)} open" + (f": {', '.join(open_)}" if open_ else ""))
    if cap.dropped:
        _say(f"warning: {cap.dropped} frames dropped by the writer")
    return outcomes


def _target(rrd: Path | None, spawn: bool, serve: bool) -> Any:
    from depthstation.viz import RerunTarget

    return RerunTarget(rrd, spawn, serve)


@app.command()
def warmup(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
           resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
           serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
           interval: float = typer.Option(10.0, "--interval", help="seconds between temperature samples"),
           accelerate: float = typer.Option(1.0, "--accelerate",
                                            help="simulated camera only: run the clock this much faster"),
           ) -> None:
    """Stream until the temperature settles (protocol's warm-up rule); the curve goes into the session."""
    st = Station(camera, protocol, session, resume, seed, real_time)
    do_warmup(st, interval, accelerate, _target(rrd, spawn, serve))


@app.command()
def calibrate(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
              resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
              serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
              write: bool = typer.Option(False, "--write", help="also write an applied table to the EEPROM")
              ) -> None:
    """On-chip and tare calibration; shows the health values, applies a table only when confirmed."""
    st = Station(camera, protocol, session, resume, seed, real_time)
    do_calibrate(st, yes, write)


@app.command()
def capture(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
            resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
            serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
            max_guidance: float | None = typer.Option(None, "--max-guidance",
                                                      help="give up a standpoint after this many seconds")
            ) -> None:
    """Guided standpoints: follow the instructions; each standpoint is recorded into one MCAP."""
    st = Station(camera, protocol, session, resume, seed, real_time)
    do_capture(st, _target(rrd, spawn, serve), max_guidance)


@app.command("session")
def session_cmd(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
                resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt,
                spawn: bool = SpawnOpt, serve: bool = ServeOpt, seed: int = SeedOpt,
                real_time: bool = RealTimeOpt,
                interval: float = typer.Option(10.0, "--interval", help="seconds between warm-up samples"),
                accelerate: float = typer.Option(1.0, "--accelerate",
                                                 help="simulated camera only: warm-up clock speed-up"),
                skip_warmup: bool = typer.Option(False, "--skip-warmup", help="camera is warm already"),
                max_guidance: float | None = typer.Option(
                    None, "--max-guidance", help="give up a standpoint after this many seconds"),
                ) -> None:
    """Warm-up, calibration and capture in order; with --resume, the steps done already are skipped."""
    st = Station(camera, protocol, session, resume, seed, real_time)
    target = _target(rrd, spawn, serve)
    if st.session.data.get("warmup") is None and not skip_warmup:
        if st.spec.kind == "file":
            st.session.set("warmup", {"done": False, "reason": "recording: no warm-up possible"})
        else:
            do_warmup(st, interval, accelerate, target)
    if st.session.data.get("calibration") is None:
        do_calibrate(st, yes, write=False)
    do_capture(st, target, max_guidance)
