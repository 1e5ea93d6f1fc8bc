"""The `evaluate checkerboard` workflow: open inputs, evaluate each standpoint, write the folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from depthstation.board import load_board
from depthstation.errors import EvaluationError, InputError
from depthstation.viz import RerunTarget, recording
from evaluate.checkerboard import rerun_log
from evaluate.checkerboard.report import standpoint_row, write_study
from evaluate.checkerboard.study import StandpointResult, evaluate_recording


def run_study(inputs: list[Path], board_path: Path, out: Path, *, frames: int = 150,
              reference: str = "auto", target: RerunTarget | None = None,
              collect_samples: bool = False, workers: int = 1,
              cluster: str | None = None) -> list[dict[str, Any]]:
    """Evaluate every standpoint in `inputs`; returns the rows of standpoints.csv.

    With `workers > 1` or a Dask `cluster`, standpoints go out as tasks (each read by the worker
    that evaluates it); the per-frame rerun stream then shows standpoints, not frames.
    """
    from depthstation.capture.reader import open_inputs
    from depthstation.progress import progress

    if reference not in ("auto", "average", "frame"):
        raise InputError(None, f"--reference must be auto, average or frame, not '{reference}'")
    board = load_board(board_path)
    recs = open_inputs(inputs)
    if not recs:
        raise InputError(inputs[0] if inputs else None, "no standpoints found")
    target = target or RerunTarget()
    with recording("depthstation_checkerboard", target, rerun_log.study_blueprint(),
                   rerun_log.DESCRIPTION) as rec, progress() as bar:
        total = sum(min(r.frame_count or frames, frames) for r in recs)
        task = bar.add_task("checkerboard", total=total, status="")
        if workers > 1 or cluster is not None:
            from evaluate.batch import run_checkerboard

            bar.update(task, total=len(recs), status=f"{len(recs)} standpoints on workers")

            def on_chunk(done: int, total: int) -> None:
                bar.update(task, completed=done)

            results = run_checkerboard(inputs, board, frames=frames, workers=workers, cluster=cluster,
                                       progress=on_chunk, reference=reference,
                                       collect_samples=collect_samples)
            for i, result in enumerate(results):
                rerun_log.log_standpoint(rec, i, result)
        else:
            results = _serial(recs, board, frames, reference, collect_samples, rec, bar, task)
        rows = [standpoint_row(x) for x in results]
        rerun_log.log_table(rec, rows)
    if not any(x.usable for x in results):
        reasons = sorted({k for x in results for k in x.rejected})
        msg = (f"no usable frame in any of {len(results)} standpoints ({', '.join(reasons) or 'no frames'}); "
               f"does {board_path} describe the printed board (type, squares, dictionary)?")
        raise EvaluationError(msg)
    first = recs[0]
    device = dict(first.metadata.get("device") or first.info.device or {})
    params = {"board": str(board_path), "frames": frames, "reference": reference,
              "margin_m": 0.01, "pose": "EPnP + LM (IPPE fallback)"}
    write_study(out, results, board, [str(p) for p in inputs], params, device)
    return rows


def _serial(recs: list[Any], board: Any, frames: int, reference: str, collect_samples: bool,
            rec: Any, bar: Any, task: Any) -> list[StandpointResult]:
    """Standpoints one after the other in this process, streaming every frame to rerun."""
    results: list[StandpointResult] = []
    step = 0
    for i, r in enumerate(recs):
        bar.update(task, status=r.name)

        def on_frame(fs: Any, res: Any, name: str = r.name, units: float = r.info.depth_units_m) -> None:
            nonlocal step
            rerun_log.log_frame(rec, step, name, fs, res, units)
            step += 1
            bar.advance(task)

        result = evaluate_recording(r, board, frames=frames, reference=reference,
                                    collect_samples=collect_samples, on_frame=on_frame)
        results.append(result)
        rerun_log.log_standpoint(rec, i, result)
    return results
