"""`depthstation acquire`: warm-up, on-device calibration and guided capture into a session.

Thin commands: parse the options, then call the station's workflows (`acquire.station`), which the
demo calls too. Every command takes `--camera live|PATH|sim[:MODEL]`, `--protocol`, `--session DIR`,
`--resume`, `--yes` and the rerun options. `--yes` also lets a live camera enable advanced mode
(it resets once); without it the operator is asked.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import click
import typer

from depthstation.acquire.station import (
    Station,
    acquire_rrd,
    do_calibrate,
    do_capture,
    do_warmup,
    redo_warmup_if_cooled,
    session_run_view,
)
from depthstation.core.rerun_bridge import RerunTarget

app = typer.Typer(no_args_is_help=True, help="Warm-up, on-device calibration and guided capture.")

CameraOpt = typer.Option("sim", "--camera", help="live, live:SERIAL, a .db3/.bag recording, or sim[:MODEL]")
ProtocolOpt = typer.Option(None, "--protocol",
                           help="protocol name in protocols/ or a TOML path (default checkerboard-d455; "
                                "--resume uses the session's stored one)")
SessionOpt = typer.Option(..., "--session", help="session directory (created; or continued with --resume)")
ResumeOpt = typer.Option(False, "--resume", help="continue an interrupted session")
YesOpt = typer.Option(False, "--yes", "-y", help="answer yes to every question (scripts)")
RrdOpt = typer.Option(None, "--rrd", help="write the live view to this .rrd file (--resume with an "
                      "existing one writes NAME.resume-N.rrd beside it)")
SpawnOpt = typer.Option(False, "--spawn", help="open a rerun viewer")
ServeOpt = typer.Option(False, "--serve", help="serve a local rerun web viewer")
SeedOpt = typer.Option(0, "--seed", help="seed of the simulated camera and operator")
RealTimeOpt = typer.Option(False, "--real-time",
                           help="pace a simulated camera or a recording at its frame rate")


def _ask(question: str) -> bool:
    return typer.confirm(question, default=False, err=True)


def _choose(question: str) -> str:
    """retry / skip / abort after a failed self-calibration."""
    return str(typer.prompt(question, default="retry", type=click.Choice(["retry", "skip", "abort"]),
                            err=True))


def _ask_distance(question: str, default: float) -> float:
    return float(typer.prompt(question, default=default, type=float, err=True))


def _consent(yes: bool) -> Callable[[str], bool]:
    """The operator's yes to a question the camera asks (enable advanced mode): --yes or a prompt."""
    return (lambda question: True) if yes else _ask


WriteOpt = typer.Option(False, "--write", help="also write an applied table to the device's flash "
                        "(else it lives in RAM and is set again after every reconnect)")


def _target(rrd: Path | None, spawn: bool, serve: bool, resume: bool) -> RerunTarget:
    """The rerun target, checked before any work; a resume never overwrites the earlier .rrd."""
    if rrd is not None:
        rrd = acquire_rrd(rrd, resume)
    return RerunTarget(rrd, spawn, serve)


@app.command()
def warmup(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
           resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
           serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
           interval: float = typer.Option(10.0, "--interval", help="seconds between temperature samples"),
           accelerate: float = typer.Option(1.0, "--accelerate",
                                            help="simulated camera only: run the clock this much "
                                                 "faster (>= 1)"),
           ) -> None:
    """Stream until the temperature settles (protocol's warm-up rule); the curve goes into the session."""
    target = _target(rrd, spawn, serve, resume)
    st = Station(camera, protocol, session, resume, seed, real_time, confirm=_consent(yes),
                 accelerate=accelerate, warmup_interval_s=interval)
    try:
        do_warmup(st, interval, accelerate, target)
    finally:
        st.close()


@app.command()
def calibrate(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
              resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
              serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
              write: bool = WriteOpt) -> None:
    """On-chip and tare calibration; shows the health values, applies a table only when confirmed."""
    st = Station(camera, protocol, session, resume, seed, real_time, confirm=_consent(yes))
    try:
        do_calibrate(st, yes, write, ask=_ask, ask_distance=_ask_distance, choose=_choose)
    finally:
        st.close()


@app.command()
def capture(camera: str = CameraOpt, protocol: str = ProtocolOpt, session: Path = SessionOpt,
            resume: bool = ResumeOpt, yes: bool = YesOpt, rrd: Path | None = RrdOpt, spawn: bool = SpawnOpt,
            serve: bool = ServeOpt, seed: int = SeedOpt, real_time: bool = RealTimeOpt,
            max_guidance: float | None = typer.Option(None, "--max-guidance",
                                                      help="give up a standpoint after this many seconds")
            ) -> None:
    """Guided standpoints: follow the instructions; each standpoint is recorded into one MCAP."""
    target = _target(rrd, spawn, serve, resume)
    st = Station(camera, protocol, session, resume, seed, real_time, confirm=_consent(yes),
                 max_guidance_s=max_guidance)
    try:
        do_capture(st, target, max_guidance)
    finally:
        st.close()


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
                write: bool = WriteOpt,
                ) -> None:
    """Warm-up, calibration and capture in order, streaming throughout; with --resume, the steps
    done already are skipped."""
    target = _target(rrd, spawn, serve, resume)
    st = Station(camera, protocol, session, resume, seed, real_time, confirm=_consent(yes),
                 accelerate=accelerate, warmup_interval_s=None if skip_warmup else interval,
                 max_guidance_s=max_guidance)
    try:
        # one rerun recording for the whole run: the warm-up and the capture go into the same .rrd
        with session_run_view(st, target) as rec:
            if resume and not skip_warmup and st.spec.kind != "file":
                redo_warmup_if_cooled(st)
            if st.session.data.get("warmup") is None and not skip_warmup:
                if st.spec.kind == "file":
                    st.session.set("warmup", {"done": False, "reason": "recording: no warm-up possible"})
                else:
                    do_warmup(st, interval, accelerate, rec)
            if st.session.data.get("calibration") is None:
                do_calibrate(st, yes, write=write, ask=_ask, ask_distance=_ask_distance, choose=_choose)
            do_capture(st, rec, max_guidance)
    finally:
        st.close()
