"""Top-level commands of this part; `register` adds them to the root app."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add this part's commands to the root `depthstation` app."""
