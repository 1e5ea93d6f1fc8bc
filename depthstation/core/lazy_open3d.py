"""Open3D, imported lazily and typed loosely (its stubs reject plain str paths and numpy masks)."""

from __future__ import annotations

import importlib
from typing import Any


def open3d() -> Any:
    """The open3d module; imported on first use so the CLI starts without it."""
    return importlib.import_module("open3d")
