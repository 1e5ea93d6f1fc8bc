"""`depthstation evaluate`: the studies' commands (each thin, in its study's `cli` module) in one app."""

from __future__ import annotations

import typer

from depthstation.evaluate.batch_cli import batch_command
from depthstation.evaluate.checkerboard.cli import checkerboard
from depthstation.evaluate.scan.cli import scan

app = typer.Typer(no_args_is_help=True)
app.command("checkerboard")(checkerboard)
app.command("scan")(scan)
app.command("batch")(batch_command)
