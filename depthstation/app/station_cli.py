"""Top-level commands of this part (`demo`, `view`, `compare`); `register` adds them to the root app."""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.app.compare_report import run_compare
from depthstation.app.demo import run_demo
from depthstation.app.demo_steps import DEMO_STEPS
from depthstation.app.view import view_path
from depthstation.core.progress import stderr_console
from depthstation.core.rerun_bridge import RerunTarget
from depthstation.core.results import ForceOption

RRD_HELP = "Write a rerun recording to this .rrd file."
SPAWN_HELP = "Open a rerun viewer and stream to it."
SERVE_HELP = "Serve a rerun web viewer on localhost and stream to it."


def demo(
    out: Path = typer.Option(Path("depthstation-demo"), "--out",
                             help="Folder for everything the demo makes."),
    rrd: bool = typer.Option(True, "--rrd/--no-rrd",
                             help="Write an .rrd recording per study into its folder (default) and print "
                                  "the command that opens each."),
    spawn: bool = typer.Option(False, "--spawn", help=SPAWN_HELP),
    serve: bool = typer.Option(False, "--serve", help=SERVE_HELP),
    skip: list[str] = typer.Option([], "--skip", help="Leave out a step by name (session, checkerboard, "
                                                       "scan, explain, compare)."),
) -> None:
    """The whole station on the simulated D455, no camera needed: a guided session, the checkerboard
    study of it, a reference-scan study of a simulated room walk, and explain on a concealed effect."""

    run_demo(out, rrd=rrd, spawn=spawn, serve=serve, skip=set(skip), steps=DEMO_STEPS)


def view(
    path: Path = typer.Argument(..., help="A result folder or an .rrd file."),
    spawn: bool = typer.Option(False, "--spawn",
                               help="Open the native viewer (default when --serve is not given)."),
    serve: bool = typer.Option(False, "--serve", help=SERVE_HELP),
    rrd: Path | None = typer.Option(None, "--rrd", help="For a result folder: write the recording here "
                                                          "(default: <folder>/view.rrd)."),
    force: bool = typer.Option(False, "--force", help="Rebuild a result folder's recording made before."),
) -> None:
    """Open a result in the rerun viewer; a result folder is first turned into a recording."""

    view_path(path, spawn=spawn or not serve, serve=serve, rrd=rrd, force=force)


def compare(
    dirs: list[Path] = typer.Argument(..., help="Result folders of one kind; the first is the reference."),
    out: Path = typer.Option(..., "--out", help="Folder for the comparison."),
    min_count: int = typer.Option(2000, "--min-count", help="Scan grids: compare cells with at least this "
                                                            "many samples in both (paper: 2000)."),
    match: str = typer.Option("auto", "--match", help="Checkerboard standpoints: auto, name or nearest."),
    max_offset: float = typer.Option(1.0, "--max-offset", help="Nearest match: largest offset in units of "
                                                               "10 cm distance / 5 deg inclination."),
    rrd: Path | None = typer.Option(None, "--rrd", help=RRD_HELP),
    spawn: bool = typer.Option(False, "--spawn", help=SPAWN_HELP),
    serve: bool = typer.Option(False, "--serve", help=SERVE_HELP),
    force: ForceOption = False,
) -> None:
    """Put evaluations side by side: tables (CSV, printed) and difference heatmaps (PNG)."""

    run_compare(dirs, out, min_count=min_count, match=match, max_offset=max_offset,
                target=RerunTarget(rrd, spawn, serve, force), force=force)
    stderr_console.print(f"comparison written to {out}")


def register(app: typer.Typer) -> None:
    """Add this part's commands to the root `depthstation` app."""
    app.command("demo")(demo)
    app.command("view")(view)
    app.command("compare")(compare)
