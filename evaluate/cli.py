"""`depthstation evaluate`: the studies' commands (each thin, in its study's `cli` module) in one app."""

from __future__ import annotations

from typing import TYPE_CHECKING

import typer

from depthstation.core.lazy_commands import lazy_group

if TYPE_CHECKING:  # the modules COMMANDS loads, named here so that the import graph shows them
    import depthstation.evaluate.batch_cli
    import depthstation.evaluate.checkerboard.cli
    import depthstation.evaluate.scan.cli  # noqa: F401

# each command's module is imported when the command runs: `evaluate checkerboard` does not load
# the scan study (its rasteriser and registration) nor batch
COMMANDS = {"checkerboard": "depthstation.evaluate.checkerboard.cli:checkerboard",
            "scan": "depthstation.evaluate.scan.cli:scan",
            "batch": "depthstation.evaluate.batch_cli:batch_command"}
app = typer.Typer(cls=lazy_group(COMMANDS), no_args_is_help=True)
