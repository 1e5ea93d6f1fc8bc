"""Commands of this stage (thin: load, call the pure functions, write results)."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(no_args_is_help=True)


# ------------------------------------------------------------------------- checkerboard (issue 4)
@app.command()
def checkerboard(
    inputs: list[Path] = typer.Argument(..., help="Session dirs, .mcap/.bag/.db3 files, PNG folders."),
    board: Path = typer.Option(..., "--board", help="Board JSON or protocol TOML."),
    out: Path = typer.Option(..., "--out", help="Result folder (created)."),
    frames: int = typer.Option(150, "--frames", min=1, help="First N frames per standpoint."),
    reference: str = typer.Option("auto", "--reference",
                                  help="Accuracy against the 'average' pose, each 'frame' pose, or "
                                       "'auto' (average unless the camera moved)."),
    rrd: Path | None = typer.Option(None, "--rrd", help="Write a rerun recording."),
    spawn: bool = typer.Option(False, "--spawn", help="Stream to a rerun viewer."),
    serve: bool = typer.Option(False, "--serve", help="Serve a local rerun web viewer."),
    workers: int = typer.Option(1, "--workers", min=1,
                                help="Local worker processes (standpoints in parallel)."),
    cluster: str | None = typer.Option(None, "--cluster",
                                       help="Address of a Dask distributed scheduler (tcp://host:8786)."),
) -> None:
    """The checkerboard study (paper Section 3.1): noise and accuracy per standpoint."""
    from depthstation.viz import RerunTarget
    from evaluate.checkerboard.run import run_study

    rows = run_study(inputs, board, out, frames=frames, reference=reference,
                     target=RerunTarget(rrd, spawn, serve), workers=workers, cluster=cluster)
    typer.echo(f"{len(rows)} standpoints -> {out / 'standpoints.csv'}")


# ------------------------------------------------------------------------- scan (issue: scan study)
from evaluate.scan.cli import scan as _scan  # noqa: E402

app.command("scan")(_scan)

# ------------------------------------------------------------------------- batch (scale-out)
from evaluate.batch_cli import register as _register_batch  # noqa: E402

_register_batch(app)
