"""Errors of the checkerboard study."""

from __future__ import annotations

from depthstation.core.errors import InputError


class BoardMismatchError(InputError):
    """The images show a board other than the one described (colours, pattern flag, dictionary)."""
