"""The console script run in-process, as a user's shell runs it: exit code, stdout, stderr."""

from __future__ import annotations

import sys

import pytest


def run_console(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """`depthstation ARGS` through the console script's main(): (exit code, stdout, stderr)."""
    from depthstation.app import cli

    old = sys.argv
    sys.argv = ["depthstation", *args]
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    finally:
        sys.argv = old
    captured = capsys.readouterr()
    return code, captured.out, captured.err
