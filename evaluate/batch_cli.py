"""`depthstation evaluate batch MANIFEST.toml [--cluster ADDRESS] [--workers N]` (thin command)."""

from __future__ import annotations

from pathlib import Path

import typer

from depthstation.evaluate.batch import batch

WORKERS_HELP = "Local worker processes for the chunks (1 = in this process)."
CLUSTER_HELP = ("Address of an existing Dask distributed scheduler (tcp://host:8786); "
                "needs the 'cluster' extra.")


def batch_command(
    manifest: Path = typer.Argument(..., help="Manifest TOML: items with kind, inputs, options, out."),
    cluster: str | None = typer.Option(None, "--cluster", help=CLUSTER_HELP),
    workers: int = typer.Option(1, "--workers", min=1, help=WORKERS_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bars."),
) -> None:
    """Run many scan/checkerboard evaluations; finished items are not redone; grids are combined."""

    report = batch(manifest, cluster=cluster, workers=workers, progress=not quiet,
                   log=lambda s: typer.echo(s, err=True))
    typer.echo(f"{len(report.done)} evaluated, {len(report.skipped)} already finished; "
               f"results in {report.out}")
    if report.combined is not None:
        typer.echo(f"combined grid: {report.combined}")
