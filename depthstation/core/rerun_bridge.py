"""Where a command's rerun recording goes (an `.rrd` file, a spawned viewer, a local web viewer), and
the few `send_*` helpers and blueprint pieces every stage uses, so that all recordings look alike:
heatmaps over distance x inclination with named, unit-carrying axes, progress series, and a text
document that tells the viewer what it is looking at."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import DepthstationError
from depthstation.core.heatmaps import colorize
from depthstation.core.progress import stderr_console
from depthstation.core.results import check_new_file, finish_file, new_file

DESCRIPTION_PATH = "description"
DISTANCE_DIM = "distance [m]"
INCLINATION_DIM = "inclination [deg]"


@dataclass(frozen=True)
class RerunTarget:
    """The `--rrd FILE`, `--spawn` and `--serve` options of a command."""

    rrd: Path | None = None
    spawn: bool = False
    serve: bool = False
    force: bool = False  # replace an existing .rrd (only once the new one is complete)

    def __post_init__(self) -> None:
        if self.rrd is not None:  # refused now, not after the study it records
            check_new_file(Path(self.rrd), force=self.force)

    @property
    def enabled(self) -> bool:
        return self.rrd is not None or self.spawn or self.serve

    def within(self, out: Path, tmp: Path) -> RerunTarget:
        """The same target with an .rrd inside the result folder `out` written into its temporary
        folder `tmp` (the folder is renamed into place as a whole)."""
        if self.rrd is None:
            return self
        try:
            rel = Path(self.rrd).resolve().relative_to(Path(out).resolve())
        except ValueError:
            return self
        return replace(self, rrd=Path(tmp) / rel, force=True)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rerun_executable() -> str:
    """The `rerun` viewer binary of this environment (next to the Python running us, else on PATH)."""
    here = Path(sys.executable).with_name("rerun")
    if here.is_file():
        return str(here)
    found = shutil.which("rerun")
    if found is None:

        msg = "the rerun viewer executable was not found (is rerun-sdk installed?)"
        raise DepthstationError(msg)
    return found


def has_display() -> bool:
    """Whether a native viewer window can open (on Linux it needs X11 or Wayland)."""

    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _wait_for_port(port: int, timeout_s: float = 15.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.1)
    return False


def start_web_server(paths: Sequence[Path] = ()) -> tuple[str, subprocess.Popen[bytes], str]:
    """Start a detached rerun web viewer bound to 127.0.0.1 (gRPC proxy plus HTTP viewer).

    We run the viewer binary with `--bind 127.0.0.1` rather than the SDK's `serve_grpc`, because the
    SDK gives no say over the bind address and the station must not expose data on the network.
    Returns (grpc proxy url, process, browser url). The server outlives the command so the user can
    keep looking; its pid is printed so it can be stopped.
    """
    grpc_port, web_port = _free_port(), _free_port()
    cmd = [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc_port),
           "--web-viewer-port", str(web_port), *[str(p) for p in paths]]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    proxy = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
    if not (_wait_for_port(grpc_port) and _wait_for_port(web_port)):  # the browser url answers once returned
        proc.terminate()

        msg = f"the rerun web viewer did not start (tried: {' '.join(cmd)})"
        raise DepthstationError(msg)
    browser = f"http://127.0.0.1:{web_port}/?url={proxy}"
    return proxy, proc, browser


def _announce(text: str) -> None:

    stderr_console.print(text)


@contextmanager
def recording(app_id: str, target: RerunTarget, blueprint: Any = None,
              description: str | None = None, recording_id: str | None = None) -> Iterator[Any]:
    """Yield a rerun RecordingStream (or None when no target is set); flushed and closed on exit.

    rerun is imported only when a target is set, so commands without `--rrd` never pay for it.
    The web viewer binds to localhost only. The description goes to the entity `description` as a
    markdown TextDocument (every recording should explain itself). The same `recording_id` in
    several .rrd files makes the viewer show them as one recording (a resumed session).
    """
    if not target.enabled:
        yield None
        return
    import rerun as rr

    rec = rr.RecordingStream(app_id, recording_id=recording_id)
    sinks: list[Any] = []
    partial: Path | None = None
    if target.rrd is not None:  # written under a temporary name, renamed when complete
        partial = new_file(Path(target.rrd), force=target.force)
        sinks.append(rr.FileSink(str(partial)))
    if target.spawn and not has_display():
        _announce("no display found, so no viewer window can open: use --serve for a web viewer "
                  "or --rrd FILE and open it later")
    elif target.spawn:
        port = _free_port()
        rr.spawn(port=port, connect=False, executable_path=rerun_executable(), default_blueprint=blueprint)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
    if target.serve:
        proxy, proc, browser = start_web_server()
        sinks.append(rr.GrpcSink(proxy))
        _announce(f"rerun web viewer: {browser}  (server pid {proc.pid}; stop it with `kill -- -{proc.pid}`)")
    if not sinks:
        yield None
        return
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    if description:
        send_text(rec, DESCRIPTION_PATH, description)
    try:
        yield rec
    except BaseException:
        rec.flush()
        rec.disconnect()
        if partial is not None:
            partial.unlink(missing_ok=True)
        raise
    rec.flush()
    rec.disconnect()
    if partial is not None and target.rrd is not None:
        finish_file(partial, Path(target.rrd))


# ---------------------------------------------------------------------------------------- send_*

def send_text(rec: Any, path: str, markdown: str) -> None:
    """A static markdown document (what the recording shows, how to read it)."""
    if rec is None:
        return
    import rerun as rr

    rec.log(path, rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)


def send_heatmap(rec: Any, path: str, values: np.ndarray, distance_edges_m: np.ndarray,
                 inclination_edges_deg: np.ndarray, *, quantity: str, unit: str,
                 step: int | None = None, timeline: str = "step") -> None:
    """A distance x inclination grid as an `rr.Tensor` whose dimensions carry names and units.

    Empty or masked cells are NaN. The bin edges, the quantity and its unit ride along as AnyValues
    on the same entity, so a reader of the `.rrd` can rebuild the axes. With `step`, the grid is
    logged on `timeline` (a growing grid); without, statically.
    """
    if rec is None:
        return
    import rerun as rr

    grid = np.asarray(values, dtype=np.float32)
    d_edges = np.asarray(distance_edges_m, dtype=np.float64)
    i_edges = np.asarray(inclination_edges_deg, dtype=np.float64)
    if grid.shape != (d_edges.size - 1, i_edges.size - 1):
        msg = f"grid shape {grid.shape} does not match the edges ({d_edges.size - 1}, {i_edges.size - 1})"
        raise ValueError(msg)
    static = step is None
    if step is not None:
        rec.set_time(timeline, sequence=int(step))
    rec.log(path, rr.Tensor(grid, dim_names=(DISTANCE_DIM, INCLINATION_DIM)), static=static)
    rec.log(path, rr.AnyValues(quantity=quantity, unit=unit,
                               distance_edges_m=d_edges, inclination_edges_deg=i_edges), static=True)


def send_colormapped(rec: Any, path: str, values: np.ndarray, *, vmin: float | None = None,
                     vmax: float | None = None, cmap: str = "viridis") -> None:
    """A 2-D field (per-pixel noise, an error map) as an `rr.Image` through a colormap."""
    if rec is None:
        return
    import rerun as rr

    rec.log(path, rr.Image(colorize(values, vmin, vmax, cmap)))


def send_series(rec: Any, path: str, index: Sequence[float] | np.ndarray,
                values: Sequence[float] | np.ndarray, *, name: str, unit: str,
                timeline: str = "step", kind: str = "sequence") -> None:
    """A whole series at once through `send_columns` (progress, temperatures, per-frame figures).

    kind: 'sequence' (integer steps), 'duration' (seconds) or 'timestamp' (epoch ns).
    The series' label carries its unit, since time-series axes in rerun have no unit field.
    """
    if rec is None:
        return
    import rerun as rr

    idx = np.asarray(index)
    vals = np.asarray(values, dtype=np.float64)
    if kind == "sequence":
        col = rr.TimeColumn(timeline, sequence=idx.astype(np.int64))
    elif kind == "duration":
        col = rr.TimeColumn(timeline, duration=idx.astype(np.float64))
    elif kind == "timestamp":
        col = rr.TimeColumn(timeline, timestamp=idx.astype("datetime64[ns]"))
    else:
        msg = f"unknown time kind {kind!r}"
        raise ValueError(msg)
    rec.log(path, rr.SeriesLines(names=[f"{name} [{unit}]"]), static=True)
    rec.send_columns(path, indexes=[col], columns=rr.Scalars.columns(scalars=vals))


def send_scalar(rec: Any, path: str, value: float, *, step: int, timeline: str = "step") -> None:
    """One point of a series while the work runs (a live progress curve)."""
    if rec is None:
        return
    import rerun as rr

    rec.set_time(timeline, sequence=int(step))
    rec.log(path, rr.Scalars(float(value)))


def send_depth(rec: Any, path: str, depth: np.ndarray, depth_units_m: float) -> None:
    """A z16 depth image with its metres-per-unit, as rerun's D4xx example does."""
    if rec is None:
        return
    import rerun as rr

    rec.log(path, rr.DepthImage(depth, meter=1.0 / depth_units_m))


def send_table(rec: Any, path: str, rows: list[dict[str, Any]]) -> None:
    """A small table (standpoints, candidates) as a markdown document, readable in the viewer."""
    if rec is None or not rows:
        return
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for row in rows:
        cells = [f"{v:.5g}" if isinstance(v, float) else str(v) for v in (row.get(k, "") for k in keys)]
        lines.append("| " + " | ".join(cells) + " |")
    send_text(rec, path, "\n".join(lines))


# ---------------------------------------------------------------------------------------- blueprint

def heatmap_view(path: str, name: str, colormap: Any = "Turbo") -> Any:
    """A tensor view of a distance x inclination grid: inclination across, distance down."""
    import rerun.blueprint as rrb
    from rerun.encodings import TensorDimensionSelection

    return rrb.TensorView(
        origin=path, name=name,
        slice_selection=rrb.TensorSliceSelection(width=TensorDimensionSelection(1),
                                                 height=TensorDimensionSelection(0)),
        scalar_mapping=rrb.TensorScalarMapping(colormap=colormap),
    )


def series_view(origin: str, name: str) -> Any:
    """A time-series view (progress, per-frame figures)."""
    import rerun.blueprint as rrb

    return rrb.TimeSeriesView(origin=origin, name=name)


def image_view(origin: str, name: str) -> Any:
    import rerun.blueprint as rrb

    return rrb.Spatial2DView(origin=origin, name=name)


def text_view(path: str = DESCRIPTION_PATH, name: str = "About this recording") -> Any:
    import rerun.blueprint as rrb

    return rrb.TextDocumentView(origin=path, name=name)


def blueprint(*views: Any, text: bool = True) -> Any:
    """Views in a grid, with the description document beside them."""
    import rerun.blueprint as rrb

    parts = [rrb.Grid(*views)] if views else []
    if text:
        parts.append(text_view())
    return rrb.Blueprint(rrb.Horizontal(*parts, column_shares=[3, 1][: len(parts)]), collapse_panels=True)


# ---------------------------------------------------------------------------------------- reading

@dataclass
class RrdContents:
    """What an `.rrd` holds, per entity: its component columns, tensors and series, for tests and `view`."""

    entities: dict[str, set[str]]
    tensors: dict[str, tuple[tuple[int, ...], tuple[str, ...]]]
    series: dict[str, np.ndarray]
    texts: dict[str, str]
    has_blueprint: bool


def read_rrd(path: Path) -> RrdContents:
    """Read an `.rrd` back with rerun's chunk reader (`rerun.chunk.RrdReader`)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    entities: dict[str, set[str]] = {}
    tensors: dict[str, tuple[tuple[int, ...], tuple[str, ...]]] = {}
    series_parts: dict[str, list[float]] = {}
    texts: dict[str, str] = {}
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        ent = str(chunk.entity_path)
        names = [n for n in batch.schema.names if not n.startswith("rerun.controls")]
        entities.setdefault(ent, set()).update(names)
        for col in names:
            if col.endswith("Tensor:data"):
                for cell in batch.column(col).to_pylist():
                    if cell:
                        tensors[ent] = (tuple(int(s) for s in cell[0]["shape"]), tuple(cell[0]["names"]))
            elif col.endswith("Scalars:scalars"):
                for cell in batch.column(col).to_pylist():
                    if cell:
                        series_parts.setdefault(ent, []).extend(float(x) for x in cell)
            elif col.endswith("TextDocument:text"):
                for cell in batch.column(col).to_pylist():
                    if cell:
                        texts[ent] = str(cell[0])
    return RrdContents(entities=entities, tensors=tensors,
                       series={k: np.asarray(v) for k, v in series_parts.items()}, texts=texts,
                       has_blueprint=bool(reader.blueprints()))
