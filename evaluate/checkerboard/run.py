"""The `evaluate checkerboard` workflow: prepare (open the inputs once), run the standpoints, write.

One path for everyone: the command, `evaluate batch`, explain's real side and the demo call
`prepare_checkerboard`, run its standpoints on a ChunkRunner (`chunks.run_standpoints`), and
`finish_checkerboard` writes the result folder, so a batch item and the command write the same files.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.board import Board
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import check_distinct_recordings, check_lenses, open_inputs
from depthstation.core.capture.session import SESSION_FILE, Session
from depthstation.core.capture.session import camera_identity as session_camera_identity
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import InputError
from depthstation.core.frames import FrameSet
from depthstation.core.parallel import ChunkRunner
from depthstation.core.progress import progress
from depthstation.core.protocol import load_board
from depthstation.core.rerun_bridge import RerunTarget, recording
from depthstation.core.results import result_folder
from depthstation.core.run_warnings import ensure_collecting, warn
from depthstation.evaluate.checkerboard import rerun_log
from depthstation.evaluate.checkerboard.chunks import (
    REFERENCES,
    CheckerboardChunk,
    StandpointOptions,
    run_standpoints,
)
from depthstation.evaluate.checkerboard.detection import unconfirmed
from depthstation.evaluate.checkerboard.dqt import EXPECTED_SUBPIXEL_PX
from depthstation.evaluate.checkerboard.figures import preload_plotting
from depthstation.evaluate.checkerboard.frame import FrameResult
from depthstation.evaluate.checkerboard.report import standpoint_row, write_study
from depthstation.evaluate.checkerboard.study import DEFAULT_FRAMES, StandpointResult

POSE_METHOD = "EPnP + LM (IPPE fallback)"


@dataclass
class CheckerboardJob:
    """A prepared checkerboard study: the board, the standpoints' recordings (opened once)."""

    inputs: list[Path]
    board_source: str               # the board file, or a description of a board given in code
    board: Board
    recordings: list[Recording]
    options: StandpointOptions

    @property
    def chunks(self) -> list[CheckerboardChunk]:
        return [CheckerboardChunk(str(r.path), self.board, self.options) for r in self.recordings]

    @property
    def parameters(self) -> dict[str, Any]:
        o = self.options
        params: dict[str, Any] = {"board": self.board_source, "frames": o.frames, "reference": o.reference,
                                  "margin_m": o.margin_m, "pose": POSE_METHOD}
        if o.topics is not None:
            params["topics"] = o.topics.to_dict()
        if o.roi is not None:
            params["roi_pct"] = 100.0 * o.roi
        params["dqt_expected_subpixel_px"] = EXPECTED_SUBPIXEL_PX
        return params

    def caption(self, results: list[StandpointResult]) -> str:
        """What every figure title says of the data: stream resolution and frames used."""
        i = self.recordings[0].info.depth_intrinsics
        used = [r.frames_used for r in results if r.usable]
        if not used:
            return f"depth {i.width}x{i.height}, no usable frame"
        frames = f"{min(used)}-{max(used)}" if min(used) != max(used) else str(used[0])
        return f"depth {i.width}x{i.height}, {frames} frames per standpoint"

    @property
    def device(self) -> dict[str, Any]:
        first = self.recordings[0]
        return dict(first.metadata.get("device") or first.info.device or {})


def prepare_checkerboard(inputs: list[Path], board: Path | Board,
                         options: StandpointOptions | None = None, *,
                         one_camera: bool = False) -> CheckerboardJob:
    """Load the board (a board JSON or protocol TOML, or a Board), expand the inputs into
    standpoints and open each one once. With `one_camera`, standpoints of different cameras or
    modes are refused instead of warned (explain simulates every standpoint as one camera)."""
    opt = options or StandpointOptions()
    if opt.reference not in REFERENCES:
        raise InputError(None, f"--reference must be auto, average or frame, not '{opt.reference}'")
    if opt.frames is not None and opt.frames < 1:
        raise InputError(None, f"--frames must be at least 1, not {opt.frames}")
    if opt.roi is not None and not 0.0 < opt.roi <= 1.0:
        raise InputError(None, f"--roi must be a percentage in (0, 100], not {100 * opt.roi:g}")
    if opt.roi is not None and opt.roi < 0.01:  # a fraction given for a percentage
        raise InputError(None, f"--roi is a percentage of the image: {100 * opt.roi:g} % leaves a few "
                               f"pixels for the plane fit (did you mean {10000 * opt.roi:g}?); use 1 to 100")
    brd = board if isinstance(board, Board) else load_board(board)
    source = f"{brd.type} {brd.squares_x}x{brd.squares_y}, {brd.square_length_m} m squares (given)" \
        if isinstance(board, Board) else str(board)
    for p in map(Path, inputs):  # a scan walk holds no board: "found in no frame" blamed the board file
        if (p / SESSION_FILE).is_file() and "scan" in Session.open(p, read_only=True).data:
            raise InputError(p, "is a scan session (a walk past a reference, no board): evaluate it with "
                                "`evaluate scan` or `explain --scan`, giving its sequence.mcap, --poses and "
                                "--reference")
    recs = open_inputs(inputs, opt.topics)
    if not recs:
        raise InputError(inputs[0] if inputs else None, "no standpoints found")
    # results, samples and explain's pairs are keyed by standpoint name: two inputs with one name
    # would be merged into one standpoint (or one would replace the other) without a word
    seen: dict[str, Path] = {}
    for r in recs:
        if r.name in seen:
            raise InputError(r.path, f"standpoint name '{r.name}' also comes from {seen[r.name]}: two "
                                     "inputs hold the same standpoint (two sessions of one protocol?); "
                                     "evaluate them in separate runs")
        seen[r.name] = r.path
    check_distinct_recordings(recs)
    for r in recs:
        check_lenses(r)
    check_recorded_board(brd, recs, source)
    check_one_camera(recs, refuse=one_camera)
    return CheckerboardJob(list(inputs), source, brd, recs, opt)


def camera_identity(rec: Recording) -> dict[str, Any]:
    """The session's camera identity (`session.camera_identity`: device name and serial, baseline,
    stream sizes) of a recording, its metadata's device where the stream info has none, and its depth
    units: what `result.json` reports as one device."""
    dev = dict(rec.metadata.get("device") or rec.info.device or {})
    ident = session_camera_identity(replace(rec.info, device=dev))
    ident["depth_units_m"] = rec.info.depth_units_m
    return ident


def check_one_camera(recs: list[Recording], *, refuse: bool = False) -> None:
    """Warn when the standpoints come from different cameras or modes (a session resumed with another
    camera, another camera's recording dropped into a session). Why: noise grows with z^2 / (f B), so
    standpoints of a D435 among D455 ones bend every fitted curve, and `result.json` names one device.
    With `refuse` it is bad input: explain would simulate them all as the first one's camera."""
    ids = [camera_identity(r) for r in recs]
    differ = sorted(k for k in ids[0] if any(x[k] != ids[0][k] for x in ids[1:]
                                             if x[k] is not None and ids[0][k] is not None))
    if not differ:
        return
    groups: dict[str, list[str]] = {}
    for r, x in zip(recs, ids, strict=True):
        groups.setdefault(", ".join(f"{k} {x[k]}" for k in differ), []).append(r.name)
    listing = "; ".join(f"{', '.join(names)}: {what}" for what, names in groups.items())
    if refuse:
        raise InputError(recs[0].path.parent, f"the standpoints come from more than one camera or mode "
                                              f"({listing}); explain simulates one camera: explain each "
                                              "camera's standpoints separately")
    warn(f"the standpoints come from more than one camera or mode ({listing}); the result names the first "
         "one: evaluate each camera separately", str(recs[0].path.parent), "mixed-cameras")


BOARD_KEYS = ("type", "squares_x", "squares_y", "square_length_m", "marker_length_m", "dictionary",
              "first_square_black")


def check_recorded_board(board: Board, recs: list[Recording], source: str) -> None:
    """Warn where the board given differs from the one the recording says it shows (the session's
    protocol, a PNG set's board.json). Why: every distance scales with the square length, so a
    print at 97 % ("fit to page") given at its nominal size, or the reverse, moves the accuracy by
    3 % of the distance, and the board-scale check (5 %) lets that through."""
    told: set[str] = set()
    for r in recs:
        rec = r.metadata.get("board")
        if not isinstance(rec, dict):
            proto = r.metadata.get("protocol")
            rec = proto.get("board") if isinstance(proto, dict) else None
        if not isinstance(rec, dict):
            continue
        diffs = []
        for key in BOARD_KEYS:
            mine, theirs = getattr(board, key), rec.get(key)
            if theirs is None or mine is None:
                continue
            if isinstance(mine, float) and isinstance(theirs, (int, float)):
                if abs(float(theirs) - mine) <= 1e-4 * abs(mine):
                    continue
            elif mine == theirs:
                continue
            diffs.append(f"{key} {theirs!r} there, {mine!r} in {source}")
        if diffs:
            text = "; ".join(diffs)
            where = str(r.path.parent)  # the session, or the PNG set's root (its board.json)
            why = ("every distance scales with the square length" if any(d.startswith("square_length_m")
                                                                          for d in diffs)
                   else "the board's centre, area and corners follow its description")
            if text not in told:
                told.add(text)
                warn(f"the recording's board differs from the one given: {text} ({why}: which one is the "
                     "print?)", where, "board-mismatch")


def check_usable(job: CheckerboardJob, results: list[StandpointResult]) -> None:
    """No usable frame anywhere is bad input (exit 2): the board file does not describe the print,
    or the recordings do not show it; the line names the likely cause."""
    if not any(x.usable for x in results):
        reasons = sorted({k for x in results for k in x.rejected})
        if reasons == ["board not found"]:
            raise InputError(job.board_source if Path(job.board_source).exists() else None,
                             f"the board was found in no frame of the {len(results)} standpoint(s): does "
                             "this board file describe the printed board (type, squares, dictionary)?")
        paths = ", ".join(x.path for x in results[:3] if x.path) + (", ..." if len(results) > 3 else "")
        cause = ("; a reprojection error that large means the colour image's intrinsics (a PNG set's "
                 "camera.json, the recording's calibration) do not fit its lens, or the board file's "
                 "sizes do not fit the print" if any(k.startswith("reprojection") for k in reasons) else "")
        raise InputError(None, f"no usable frame in any of {len(results)} standpoints ({paths}: "
                               f"{', '.join(reasons) or 'no frames'}){cause}; check the inputs and "
                               f"{job.board_source}")


def say_warnings(results: list[StandpointResult]) -> None:
    """Every standpoint's warnings to the run (board not found, camera moved, board scale, ...)."""
    for r in results:
        for w in r.warnings:
            warn(w.message, w.where, w.code)
        if r.usable:  # some frames were rejected; the standpoint stands on the others
            for status, n in sorted(r.rejected.items()):
                if unconfirmed(status):  # said with what it means for the pose (corner-unconfirmed)
                    continue
                code = "board-not-found" if status == "board not found" else "frames-rejected"
                warn(f"{status} in {n} of {r.frames_read} frames", r.name, code)
    read = [r.frames_read for r in results if r.frames_requested is None]
    typical = float(np.median(read)) if read else 0.0
    for r in results:  # no number asked: a standpoint much shorter than its siblings was cut short
        if r.frames_requested is None and r.frames_read < 0.5 * typical:
            warn(f"{r.frames_read} frames where the standpoints of this set hold a median of {typical:.0f} "
                 "(a capture cut short?)", r.name, "fewer-frames")


def finish_checkerboard(job: CheckerboardJob, results: list[StandpointResult],
                        out: Path, *, figures: bool = True) -> list[dict[str, Any]]:
    """Write the result folder of finished standpoints (`figures`: with its PNGs); the rows of
    standpoints.csv."""
    say_warnings(results)
    check_usable(job, results)
    write_study(out, results, job.board, [str(p) for p in job.inputs], job.parameters, job.device,
                figures=figures, caption=job.caption(results))
    return [standpoint_row(x) for x in results]


def run_checkerboard(inputs: list[Path], board_path: Path, out: Path, *, frames: int | None = None,
                     reference: str = "auto", target: RerunTarget | None = None,
                     collect_samples: bool = False, workers: int = 1,
                     cluster: str | None = None, force: bool = False, topics: TopicChoice | None = None,
                     roi_pct: float | None = None, figures: bool = True) -> list[dict[str, Any]]:
    """The checkerboard study (paper Section 3.1) of every standpoint in `inputs` into `out`
    (written whole or not at all; a non-empty `out` only with `force`; `figures`: with its PNGs).

    With `workers > 1` or a Dask `cluster`, standpoints go out as tasks (each read by the worker
    that evaluates it); the per-frame rerun stream then shows standpoints, not frames.
    """
    options = replace(StandpointOptions(), frames=frames, reference=reference,
                      collect_samples=collect_samples, topics=topics,
                      roi=None if roi_pct is None else roi_pct / 100.0)
    with ensure_collecting():  # what preparing the job warns (the board) is the run's too
        job = prepare_checkerboard(inputs, board_path, options)
        with result_folder(out, force=force, inputs=[*inputs, board_path], kind="checkerboard") as tmp:
            return _run(job, tmp, (target or RerunTarget()).within(out, tmp), workers, cluster, figures)


def _run(job: CheckerboardJob, out: Path, target: RerunTarget, workers: int,
         cluster: str | None, figures: bool = True) -> list[dict[str, Any]]:
    frames = job.options.frames or DEFAULT_FRAMES
    recs = job.recordings
    # the figures' plotting library loads while the standpoints are evaluated (their threads
    # spend their time in native code), not after them
    if figures:
        threading.Thread(target=preload_plotting, daemon=True).start()
    blueprint = rerun_log.study_blueprint() if target.enabled else None  # rerun loads only when used
    with ChunkRunner(workers, cluster) as runner, \
            recording("depthstation_checkerboard", target, blueprint, rerun_log.DESCRIPTION) as rec, \
            progress() as bar:
        total = (sum(min(r.frame_count or frames, frames) for r in recs) if runner.in_process
                 else len(recs))
        task = bar.add_task("checkerboard", total=total,
                            status="" if runner.in_process else f"{len(recs)} standpoints on workers")
        step = [0]
        lock = threading.Lock()

        def frame_hook(r: Recording) -> Any:
            bar.update(task, status=r.name)

            def on_frame(fs: FrameSet, res: FrameResult) -> None:  # from the standpoints' threads
                with lock:
                    k = step[0]
                    step[0] += 1
                rerun_log.log_frame(rec, k, r.name, fs, res, r.info.depth_units_m)
                bar.advance(task)
            return on_frame

        def on_chunks(done: int, n: int) -> None:
            if not runner.in_process:
                bar.update(task, completed=done)

        results = run_standpoints(recs, job.board, job.options, runner, on_frame=frame_hook,
                                  on_standpoint=lambda i, r: rerun_log.log_standpoint(rec, i, r),
                                  progress=on_chunks)
        rerun_log.log_table(rec, [standpoint_row(x) for x in results])
    return finish_checkerboard(job, results, out, figures=figures)
