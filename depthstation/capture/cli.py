"""Commands of this stage (thin: load, call the pure functions, write results)."""

from __future__ import annotations

import typer

app = typer.Typer(no_args_is_help=True)
