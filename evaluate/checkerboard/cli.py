"""`depthstation evaluate checkerboard`: a thin typer command over `run.run_checkerboard`."""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.core.capture.topics import ColorTopic, DepthTopic, InfraredTopic, topic_choice
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import ForceOption
from depthstation.evaluate.checkerboard.run import run_checkerboard


def checkerboard(
    inputs: list[Path] = typer.Argument(..., help="Session dirs, .mcap/.bag/.db3 files, PNG folders."),
    board: Path = typer.Option(..., "--board", help="Board JSON or protocol TOML."),
    out: Path = typer.Option(..., "--out", help="Result folder (created)."),
    frames: int | None = typer.Option(None, "--frames", min=1,
                                      help="First N frames per standpoint; a standpoint with fewer is "
                                           "warned of. Default: up to 150 (the paper's), no warning."),
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
    roi: float | None = typer.Option(None, "--roi", help="Also Intel's Depth Quality Tool metrics on a "
                                                        "centred ROI of this percentage of each side "
                                                        "(DQT: 40), besides the board mask."),
    depth_topic: DepthTopic = None,
    color_topic: ColorTopic = None,
    infrared_topic: InfraredTopic = None,
    force: ForceOption = False,
    no_figures: bool = typer.Option(False, "--no-figures",
                                    help="Skip the PNG figures (the tables, summary and result.json are "
                                         "written as ever; the figures take most of a small study's time)."),
) -> None:
    """The checkerboard study (paper Section 3.1): noise and accuracy per standpoint, with Intel's
    Depth Quality Tool metrics (dqt_* columns) beside them."""
    rows = run_checkerboard(inputs, board, out, frames=frames, reference=reference,
                            target=RerunTarget(rrd, spawn, serve, force), workers=workers, cluster=cluster,
                            force=force, topics=topic_choice(depth_topic, color_topic, infrared_topic),
                            roi_pct=roi, figures=not no_figures)
    typer.echo(f"{len(rows)} standpoints -> {out / 'standpoints.csv'}")
