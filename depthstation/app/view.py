"""`depthstation view`: a result folder becomes a recording (heatmaps, series, figures, description);
an `.rrd` opens as is, in the native viewer or a web viewer bound to localhost."""

from __future__ import annotations

import json
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core import rerun_bridge as viz
from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE, Grid
from depthstation.core.progress import stderr_console
from depthstation.core.results import (
    EXPLAIN_FILE,
    RESULT_FILE,
    RESULT_MARKER,
    STANDPOINTS_FILE,
    is_recording_rrd,
    read_result_info,
    read_standpoints,
)

MIN_COUNT_VIEW = 10
SERIES_COLUMNS = ("noise_m", "accuracy_m", "accuracy_rms_m", "fill_rate")


def _describe(folder: Path, info: dict[str, Any], parts: list[str]) -> str:
    lines = [f"# {folder.name}", "", f"Result folder `{folder}`"]
    if info:
        lines += [f"- kind: **{info.get('kind', '?')}**, created {info.get('created', '?')}",
                  f"- inputs: {', '.join(map(str, info.get('inputs', []))) or '-'}",
                  f"- device: `{json.dumps(info.get('device', {}))[:300]}`",
                  f"- parameters: `{json.dumps(info.get('parameters', {}))[:300]}`"]
    lines += ["", "## What is shown", *[f"- {p}" for p in parts], "",
              "Conventions: distance = reference z-depth (m); inclination = angle between viewing ray and "
              "surface normal (deg, 0 = head-on); errors = measured - reference (+ = too far)."]
    return "\n".join(lines)


def folder_to_rrd(folder: Path, rrd: Path, *, force: bool = False) -> Path:
    """Convert what a result folder holds into an `.rrd` with a blueprint and a description (written
    under a temporary name by the recording and renamed when complete; `force` replaces an earlier one)."""
    import rerun as rr

    folder = Path(folder)
    info: dict[str, Any] = read_result_info(folder) if (folder / RESULT_FILE).is_file() else {}
    pngs = sorted(folder.glob("*.png"))
    has = {n: (folder / n).is_file() for n in (STANDPOINTS_FILE, GRID_FILE, EXPLAIN_FILE)}
    if not (any(has.values()) or info or (folder / RESULT_MARKER).is_file()):
        # figures alone do not make a result: a folder of PNG captures would get a view.rrd written into it
        raise InputError(folder, f"not a result folder (no {RESULT_FILE}, {STANDPOINTS_FILE}, {GRID_FILE} "
                                 f"or {EXPLAIN_FILE}){'; it holds only images (a capture?)' if pngs else ''}")
    if has[EXPLAIN_FILE]:
        try:
            explain = json.loads((folder / EXPLAIN_FILE).read_text())
        except json.JSONDecodeError as exc:
            raise InputError(folder / EXPLAIN_FILE, f"broken JSON ({exc})") from exc
    parts: list[str] = []
    views: list[Any] = []
    with viz.recording(f"depthstation-view-{folder.name}", viz.RerunTarget(rrd=rrd, force=force)) as rec:
        if has[GRID_FILE]:
            g = Grid.load(folder / GRID_FILE)
            enough = g.count >= MIN_COUNT_VIEW
            viz.send_heatmap(rec, "grid/count", g.count.astype(np.float32), g.distance_edges_m,
                             g.inclination_edges_deg, quantity="samples per cell", unit="1")
            viz.send_heatmap(rec, "grid/mean", np.where(enough, g.mean_m, np.nan), g.distance_edges_m,
                             g.inclination_edges_deg, quantity="mean depth error", unit="m")
            viz.send_heatmap(rec, "grid/std", np.where(enough, g.std_m, np.nan), g.distance_edges_m,
                             g.inclination_edges_deg, quantity="std of depth error", unit="m")
            views += [viz.heatmap_view("grid/count", "samples per cell"),
                      viz.heatmap_view("grid/mean", "mean depth error [m]"),
                      viz.heatmap_view("grid/std", "std of depth error [m]")]
            parts.append(f"`grid/*`: tensors over distance [m] (rows) x inclination [deg] (columns): "
                         f"count, mean and std of the depth error in metres, cells below "
                         f"{MIN_COUNT_VIEW} samples empty")
        if has[STANDPOINTS_FILE]:
            rows = read_standpoints(folder / STANDPOINTS_FILE)
            if not rows:  # a study writes one row per standpoint: a table without any was cut
                raise InputError(folder / STANDPOINTS_FILE, "holds no standpoint (an empty or cut table)")
            idx = np.arange(len(rows))
            for col in SERIES_COLUMNS:
                if rows and col in rows[0]:
                    unit = "1" if col == "fill_rate" else "m"
                    viz.send_series(rec, f"standpoints/{col}", idx, [r[col] for r in rows], name=col,
                                    unit=unit, timeline="standpoint")
                    views.append(viz.series_view(f"standpoints/{col}", f"{col} per standpoint"))
            viz.send_table(rec, "standpoints/table", rows)
            parts.append("`standpoints/*`: per standpoint (timeline `standpoint`, table order) noise, "
                         "accuracy, fill rate; the full table as a document")
        if has[EXPLAIN_FILE]:
            viz.send_text(rec, "explain/json", "```json\n" + json.dumps(explain, indent=2)[:20000] + "\n```")
            views.append(viz.text_view("explain/json", "explain.json"))
            parts.append("`explain/json`: the mismatch found, candidates and selected effects")
        if (folder / "report.md").is_file():
            viz.send_text(rec, "explain/report", (folder / "report.md").read_text())
            views.append(viz.text_view("explain/report", "report"))
        for png in pngs:
            rec.log(f"figures/{png.stem}", rr.EncodedImage(path=png), static=True)
        if pngs:
            views.append(viz.image_view("figures", "figures"))
            parts.append("`figures/*`: the PNG figures of the folder")
        viz.send_text(rec, viz.DESCRIPTION_PATH, _describe(folder, info, parts))
        rr.send_blueprint(viz.blueprint(*views), recording=rec)
    return rrd


def _newer_than(folder: Path, rrd: Path) -> bool:
    """Whether a file of the result folder changed after its recording was made."""
    made = rrd.stat().st_mtime
    return any(p.is_file() and p != rrd and p.suffix != ".rrd" and p.stat().st_mtime > made
               for p in folder.iterdir())


def open_rrd(rrd: Path, *, spawn: bool, serve: bool) -> None:
    """Open an `.rrd`: the native viewer (detached) and/or a localhost web viewer."""

    if serve:
        _, proc, url = viz.start_web_server([rrd])
        stderr_console.print(f"web viewer: {url}\n"
                             f"(server pid {proc.pid}; stop it with `kill -- -{proc.pid}`)")
    if spawn and not viz.has_display():
        stderr_console.print(f"no display found, so no viewer window can open; the recording is {rrd}\n"
                             f"serve it with `depthstation view {rrd} --serve` (web viewer on localhost)")
    elif spawn:
        subprocess.Popen([viz.rerun_executable(), str(rrd)], start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        stderr_console.print(f"opened {rrd} in the rerun viewer")


def check_writable(folder: Path, in_result: bool) -> None:
    """A folder the recording cannot be written into, said before any work (rerun's own error named
    a temporary file, as an internal error). Probed by creating a file: permissions alone do not
    tell a read-only file system, nor what root may do."""
    if not folder.is_dir():
        return  # made by new_file; a failure there names the path
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        advice = "give --rrd a path in a folder you can write" if in_result else "choose another folder"
        raise InputError(folder, f"is not writable ({exc.strerror or exc}): no recording can be written "
                                 f"there; {advice}") from exc


def view_path(path: Path, *, spawn: bool = True, serve: bool = False, rrd: Path | None = None,
              force: bool = False) -> Path:
    """Open a result folder or an `.rrd`; returns the `.rrd` shown.

    A result folder's recording (`view.rrd` in it, or `rrd`) is made once: an existing one is
    opened as it is, and rebuilt only with `force` (written beside, then renamed over it).
    """
    path = Path(path)
    if path.is_file() and path.suffix == ".rrd":
        if not is_recording_rrd(path):
            raise InputError(path, "is not a rerun recording (no RRF header: empty, cut short at the start, "
                                   "or another file named .rrd)")
        target = path
    elif path.is_dir():
        target = Path(rrd) if rrd is not None else path / "view.rrd"
        stale = target.exists() and rrd is None and _newer_than(path, target)
        if target.exists() and not force and rrd is None and not stale:
            stderr_console.print(f"opening the recording made before, {target} (--force rebuilds it)")
        else:
            if stale:  # the folder changed since (a batch rerun updated combined/): rebuilt, not shown stale
                stderr_console.print(f"{target} is older than the result it shows; rebuilding it")
                force = True
            check_writable(target.parent, rrd is None)
            folder_to_rrd(path, target, force=force)
            stderr_console.print(f"recording of {path} written to {target}")
    else:
        raise InputError(path, "expected a result folder or an .rrd file")
    if spawn or serve:
        open_rrd(target, spawn=spawn, serve=serve)
    return target
