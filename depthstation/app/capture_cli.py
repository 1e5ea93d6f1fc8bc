"""Commands of this stage (thin: load, call the pure functions, write results)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from depthstation.core.capture.export import TARGETS, export_recordings
from depthstation.core.capture.importer import import_recordings
from depthstation.core.capture.mcap_reader import McapRecording, cut_source
from depthstation.core.capture.mcap_writer import CAPTURE_COMPRESSION, COLOR_ENCODINGS, McapFileWriter
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import open_inputs, open_recording
from depthstation.core.capture.topics import ColorTopic, DepthTopic, InfraredTopic, TopicChoice, topic_choice
from depthstation.core.errors import CaptureError, DepthstationError, InputError
from depthstation.core.progress import progress, stdout_console
from depthstation.core.results import ForceOption, _jsonable, result_folder

app = typer.Typer(no_args_is_help=True)


@app.command("import")
def import_cmd(
    sources: Annotated[
        list[Path], typer.Argument(help=".bag, .db3, .mcap files, PNG folders or dataset roots")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="new session directory")],
    compression: Annotated[str, typer.Option(help="lz4 (default: ~1.4x smaller, reads at > 300 frame "
                                                  "sets/s), zstd (~2x smaller, slower to read) or none")]
    = CAPTURE_COMPRESSION,
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
    force: ForceOption = False,
) -> None:
    """Import recordings into a capture session (one MCAP per standpoint): our MCAP, RealSense
    .bag/.db3, ROS bags (rosbag2 folders or files, ROS 1 .bag), PNG folders."""

    with progress() as bar, result_folder(out, force=force, inputs=sources, kind="capture-import") as tmp:
        session = import_recordings(sources, tmp, compression=compression, on_frame=_frame_bar(bar),
                                    topics=topic_choice(depth_topic, color_topic, infrared_topic))
    frames = sum(int(e.get("frames", 0)) for e in session.standpoints)
    typer.echo(f"{out}: {len(session.standpoints)} standpoints, {frames} frames")


def _frame_bar(bar: Any) -> Any:
    """A per-recording progress task, advanced by `on_frame(recording, index)`."""
    tasks: dict[str, Any] = {}

    def on_frame(rec: Recording, i: int) -> None:
        if rec.name not in tasks:
            tasks[rec.name] = bar.add_task(rec.name, total=rec.frame_count, status="")
        bar.update(tasks[rec.name], completed=i + 1)

    return on_frame


@app.command("export")
def export_cmd(
    sources: Annotated[list[Path], typer.Argument(help="a session, recordings or dataset roots")],
    to: Annotated[str, typer.Option("--to", help=f"target format: {' | '.join(TARGETS)}")],
    out: Annotated[Path, typer.Option("--out", "-o", help="new (or empty) folder")],
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
    force: ForceOption = False,
) -> None:
    """Export captures for other tools: a realsense-ros rosbag2 (ros2 bag play, Foxglove), a TUM
    RGB-D folder (ORB-SLAM3, RTAB-Map: make the scan study's poses) or a RealSense .db3 (Viewer).
    Written under a temporary name and renamed when complete, like every result folder."""
    recordings = open_inputs(list(sources), topic_choice(depth_topic, color_topic, infrared_topic))
    with progress() as bar, result_folder(out, force=force, inputs=sources, kind="capture-export") as tmp:
        done = export_recordings(recordings, to, tmp, on_frame=_frame_bar(bar))
    for path, n in done:
        typer.echo(f"{out / path.relative_to(tmp)}: {n} frames")


def _describe(path: Path, topics: TopicChoice | None = None) -> list[dict[str, Any]]:

    out = []
    for rec in open_inputs([path], topics):
        d = rec.summary()
        first = last = None
        n = 0
        if rec.frame_count is None or rec.frame_count <= 1000:
            times = [fs.timestamp_ns for fs in rec.frames()]  # also counts a cut-off MCAP
            n = len(times)
            if times:
                first, last = min(times), max(times)
        d["frames_read"] = n if rec.frame_count is None or rec.frame_count <= 1000 else None
        d["duration_s"] = None if first is None or last is None else (last - first) / 1e9
        out.append(d)
    return out


def _fmt_intr(d: dict[str, Any] | None) -> str:
    if d is None:
        return "-"
    return (
        f"{d['width']}x{d['height']} fx={d['fx']:.3f} fy={d['fy']:.3f} "
        f"ppx={d['ppx']:.3f} ppy={d['ppy']:.3f} {d['model']}"
    )


@app.command("info")
def info_cmd(
    path: Annotated[Path, typer.Argument(help="a recording, session directory or PNG dataset")],
    as_json: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
) -> None:
    """Streams, resolutions, frame counts, intrinsics, extrinsics, device and duration."""

    items = _describe(path, topic_choice(depth_topic, color_topic, infrared_topic))
    if as_json:
        typer.echo(json.dumps(_jsonable(items), indent=2))
        return

    console = stdout_console
    for d in items:
        info = d["info"]
        t = Table(title=f"{d['name']}  ({d['path']})", show_header=False)
        t.add_column("key", style="bold")
        t.add_column("value")
        counts = d["stream_counts"]
        t.add_row("frames", str(d["frame_count"] if d["frame_count"] is not None else d["frames_read"]))
        t.add_row("streams", ", ".join(f"{k}: {v}" for k, v in counts.items()) or "-")
        source = d["metadata"].get("source") or {}
        if source.get("kind") == "ros":
            t.add_row("topics", ", ".join(f"{k}: {v}" for k, v in source.get("topics", {}).items()))
            t.add_row("extrinsics from", str(source.get("extrinsics")))
        t.add_row("duration", "-" if d["duration_s"] is None else f"{d['duration_s']:.3f} s")
        t.add_row("fps", str(info.get("fps")))
        t.add_row("depth", _fmt_intr(info["depth_intrinsics"]))
        t.add_row("colour", _fmt_intr(info["color_intrinsics"]))
        encoding = (d["metadata"].get("format") or {}).get("color_encoding")
        if encoding and info["color_intrinsics"]:
            t.add_row("colour recorded as", f"{encoding} (read as RGB)" if encoding != "rgb8" else encoding)
        if info.get("infrared_intrinsics"):
            t.add_row("infrared", _fmt_intr(info["infrared_intrinsics"]))
        e = info["depth_to_color"]
        t.add_row("depth->colour t (m)", " ".join(f"{x:+.6f}" for x in e["translation"]))
        t.add_row("depth->colour R", " ".join(f"{x:+.6f}" for x in e["rotation"]))
        t.add_row("aligned to colour", str(info["depth_aligned_to_color"]))
        t.add_row("depth units", f"{info['depth_units_m']:g} m")
        t.add_row("baseline", "-" if info["baseline_m"] is None else f"{info['baseline_m'] * 1000:.3f} mm")
        dev = d["metadata"].get("device") or info.get("device") or {}
        t.add_row(
            "device",
            " ".join(f"{k}={dev[k]}" for k in ("name", "serial_number", "firmware_version") if k in dev)
            or "-",
        )
        console.print(t)


def _write_compact(rec: McapRecording, out: Path, compression: str) -> int:
    """Copy `rec` into `out` under a temporary name in the same folder, fsynced and linked into place
    only when complete; the temporary file is removed on any failure. Why: a full disk left a cut file
    under the final name (it read as a recording and blocked a retry). Returns the frames written."""
    if out.exists():
        raise InputError(out, "exists already; captures are never overwritten")
    tmp = out.with_name(f".{out.name}.partial-{os.getpid()}")
    temps = [(t, {k: v}) for k, (ts, vs) in rec.temperatures().items() for t, v in zip(ts, vs, strict=True)]
    color_encoding = (rec.metadata.get("format") or {}).get("color_encoding", "rgb8")  # kept as it was
    try:
        w = McapFileWriter(tmp, rec.info, {k: v for k, v in rec.metadata.items() if k != "format"},
                           compression=compression,
                           color_encoding=color_encoding if color_encoding in COLOR_ENCODINGS else "rgb8")
        try:
            for t_ns, values in temps:
                w.write_temperature(t_ns, values)
            for fs in rec.frames():
                w.write(fs)
            cut = cut_source(rec)  # a cut source makes a whole file: it still says it holds only part
            if cut is not None:
                w.add_metadata("source", dict(rec.metadata.get("source") or {}, path=str(rec.path),
                                              truncated=True, cut_path=cut["path"],
                                              recovered_frames=cut["recovered_frames"]))
            w.close()  # the summary, flushed and fsynced
        except BaseException:
            w.abort()
            raise
        _link_new(tmp, out)
        return w.frames_written
    except (OSError, CaptureError) as exc:
        cause = exc if isinstance(exc, OSError) else exc.__cause__
        if not isinstance(cause, OSError):
            raise
        raise DepthstationError(f"{out}: cannot write ({cause.strerror or cause}); the incomplete copy was "
                                f"removed and nothing was kept under {out.name} ({rec.path} is untouched)"
                                ) from exc
    finally:
        tmp.unlink(missing_ok=True)


def _link_new(tmp: Path, out: Path) -> None:
    """Give the finished `tmp` the name `out` without ever replacing a file that appeared meanwhile."""
    appeared = "appeared while compact was writing; captures are never overwritten"
    try:
        os.link(tmp, out)
    except FileExistsError as exc:
        raise InputError(out, appeared) from exc
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.EXDEV):
            raise
        if out.exists():  # a file system without hard links
            raise InputError(out, appeared) from exc
        tmp.rename(out)
    dir_fd = os.open(out.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # the new name survives a power cut
    finally:
        os.close(dir_fd)


@app.command("compact")
def compact_cmd(
    src: Annotated[Path, typer.Argument(help="an MCAP recording (ours)")],
    out: Annotated[Path, typer.Argument(help="new MCAP file")],
    compression: Annotated[str, typer.Option(help="zstd (default), lz4 or none")] = "zstd",
) -> None:
    """Rewrite a capture with stronger compression (zstd) for archiving; the source is kept."""

    if out.suffix.lower() != ".mcap":  # it writes MCAP: under another name no reader would know it
        raise InputError(out, "compact writes an MCAP recording: give the new file the .mcap suffix")
    rec = open_recording(src)
    if not isinstance(rec, McapRecording):
        raise InputError(src, "compact takes our MCAP recordings; use `capture import` for others")
    n = _write_compact(rec, out, compression)
    new_size, old_size = out.stat().st_size, src.stat().st_size
    typer.echo(f"{out}: {n} frames, {new_size / 1e6:.1f} MB (from {old_size / 1e6:.1f} MB)")
    if new_size >= old_size:  # an already compressed recording: say so rather than let 'compact' mislead
        typer.echo(f"{out}: not smaller than {src} ({new_size / old_size:.0%} of its size): the source was "
                   f"already compressed at least as well as {compression}; keeping the source loses nothing")
