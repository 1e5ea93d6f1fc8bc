"""What the operator sees: the rich terminal panel and the live rerun view of the guided capture."""

from __future__ import annotations

import time
from typing import Any

from rich.live import Live
from rich.panel import Panel
from rich.table import Table

from depthstation.acquire.guided_capture import LiveState
from depthstation.core.progress import stderr_console

BOARD_HELP = ("Point the camera at the board and follow the instructions: distance is the board "
              "centre's depth, inclination the angle between the viewing ray and the board normal.")


def panel(state: LiveState) -> Any:
    """A rich renderable: target, measured, the instruction in large type, progress."""

    sp = state.standpoint
    g = state.guidance
    t = Table.grid(padding=(0, 2))
    t.add_column(justify="right", style="bold")
    t.add_column()
    t.add_row("standpoint", f"{sp.name} ({state.index + 1}/{state.total}), trajectory {sp.trajectory + 1}")
    t.add_row("target", f"{sp.distance_m:.2f} m at {sp.inclination_deg:.0f}° ({sp.side} side)")
    if g is not None and g.seen:
        t.add_row("measured", f"{g.distance_m:.2f} m at {g.inclination_deg:.1f}°"
                  + ("" if g.fill_rate is None else f", depth on board {g.fill_rate:.0%}"))
    else:
        t.add_row("measured", "[yellow]board not in view[/]")
    styles = {"recording": "bold green", "reconnecting": "bold red", "done": "green"}
    style = styles.get(state.phase, "bold cyan")
    t.add_row("now", f"[{style}]{state.message}[/]")
    if state.phase == "recording":
        t.add_row("frames", f"{state.recorded}/{state.frames_per_standpoint}")
    t.add_row("done", ", ".join(state.done) or "-")
    if state.skipped:
        t.add_row("skipped", ", ".join(state.skipped) + " (end of range)")
    return Panel(t, title="depthstation acquire", subtitle="Ctrl-C stops; --resume continues")


class TerminalPanel:
    """Refreshes the panel at most `hz` times a second on stderr (a rich Live display)."""

    def __init__(self, hz: float = 5.0) -> None:


        self.live = Live(console=stderr_console, auto_refresh=False, transient=False)
        self.period = 1.0 / hz
        self._last = 0.0

    def __enter__(self) -> TerminalPanel:
        self.live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.live.__exit__(None, None, None)

    def __call__(self, state: LiveState) -> None:
        now = time.monotonic()
        if now - self._last < self.period and state.phase not in ("done", "reconnecting"):
            return
        self._last = now
        self.live.update(panel(state), refresh=True)


class RerunView:
    """Live rerun: colour with the detected corners, depth, distance/inclination and the messages.

    Images are logged every `every`-th frame so the viewer never slows the capture down.
    """

    def __init__(self, rec: Any, depth_units_m: float, every: int = 3) -> None:
        self.rec = rec
        self.meter = 1.0 / depth_units_m
        self.every = every
        self._n = 0
        self._last_msg = ""

    def __call__(self, state: LiveState) -> None:
        import rerun as rr

        rec, fs = self.rec, state.frame
        if rec is None or fs is None:
            return
        self._n += 1
        rec.set_time("frame", sequence=int(fs.index))
        rec.set_time("time", timestamp=fs.timestamp_ns * 1e-9)
        g = state.guidance
        if g is not None and g.seen and g.distance_m is not None and g.inclination_deg is not None:
            rec.log("measure/distance_m", rr.Scalars([g.distance_m]))
            rec.log("measure/target_distance_m", rr.Scalars([state.standpoint.distance_m]))
            rec.log("measure/inclination_deg", rr.Scalars([g.inclination_deg]))
            rec.log("measure/target_inclination_deg", rr.Scalars([state.standpoint.inclination_deg]))
        if state.message != self._last_msg:
            self._last_msg = state.message
            level = rr.TextLogLevel.WARN if state.phase == "reconnecting" else rr.TextLogLevel.INFO
            rec.log("guidance", rr.TextLog(f"[{state.standpoint.name}] {state.message}", level=level))
        if self._n % self.every and state.phase != "done":
            return
        if fs.color is not None:
            rec.log("camera/color", rr.Image(fs.color))
            if state.pose is not None:
                rec.log("camera/color/board", rr.Points2D(state.pose.corners_px, radii=2.0,
                                                          colors=[0, 255, 0]))
            else:
                rec.log("camera/color/board", rr.Clear(recursive=False))
        if fs.depth is not None:
            rec.log("camera/depth", rr.DepthImage(fs.depth, meter=self.meter))
        rec.log("progress", rr.TextDocument(
            f"**{state.standpoint.name}** ({state.index + 1}/{state.total}): {state.phase}\n\n"
            f"done: {', '.join(state.done) or '-'}", media_type=rr.MediaType.MARKDOWN))


def blueprint() -> Any:
    """Colour with the board, depth, and the distance/inclination plots beside the messages."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial2DView(origin="camera/color", name="colour + board"),
                         rrb.Spatial2DView(origin="camera/depth", name="depth")),
            rrb.Vertical(rrb.TimeSeriesView(origin="measure", name="distance (m) / inclination (deg)"),
                         rrb.TextLogView(origin="guidance", name="guidance"),
                         rrb.TimeSeriesView(origin="warmup", name="warm-up (°C, m)"),
                         rrb.TextDocumentView(origin="progress", name="progress")),
        ),
    )
