"""The `depthstation` console script: one typer app, a sub-app per stage, errors to exit codes."""

from __future__ import annotations

import gc
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click
import typer

from depthstation.core.errors import DepthstationError
from depthstation.core.lazy_commands import lazy_group
from depthstation.core.results import COMMAND_LINE, disk_error
from depthstation.core.run_warnings import RunWarning, collecting

if TYPE_CHECKING:  # the modules COMMANDS loads, named so that the import graph (layers, mypy) holds them
    import depthstation.acquire.cli
    import depthstation.app.capture_cli
    import depthstation.app.station_cli
    import depthstation.evaluate.cli
    import depthstation.evaluate.errormodel.cli
    import depthstation.evaluate.explain.cli
    import depthstation.simulate.cli  # noqa: F401

# The root's commands, in the order `--help` lists them, each from the module that defines it
# ("module:attribute", `lazy_commands.lazy_group`): a command's module is imported when the command
# runs, so `evaluate checkerboard` no longer loads the camera, the simulator's command line,
# explain and the exports (docs/checkerboard-study.md, "What the command's speed rests on").
COMMANDS: dict[str, str] = {
    "explain": "depthstation.evaluate.explain.cli:register",
    "correct": "depthstation.evaluate.errormodel.cli:register",
    "demo": "depthstation.app.station_cli:register",
    "view": "depthstation.app.station_cli:register",
    "compare": "depthstation.app.station_cli:register",
    "capture": "depthstation.app.capture_cli:app",
    "simulate": "depthstation.simulate.cli:app",
    "evaluate": "depthstation.evaluate.cli:app",
    "acquire": "depthstation.acquire.cli:app",
    "model": "depthstation.evaluate.errormodel.cli:register",
}
SUB_APP_HELP = {
    "capture": "Import, inspect and convert captures.",
    "simulate": "Render captures with the simulated D455.",
    "evaluate": "The checkerboard and reference-scan studies.",
    "acquire": "Warm-up, on-device calibration and guided capture.",
}

app = typer.Typer(
    name="depthstation",
    cls=lazy_group(COMMANDS, SUB_APP_HELP),
    help="Measure how well a depth camera measures depth over distance x inclination.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


# typer >= 0.22 carries its own copy of click: its exceptions are not click's
_USAGE: tuple[type[Exception], ...] = tuple({click.ClickException, typer.exceptions.TyperException})
_EXIT: tuple[type[BaseException], ...] = tuple({click.exceptions.Exit, typer.Exit})
_ABORT: tuple[type[BaseException], ...] = tuple({click.exceptions.Abort, typer.Abort})

STRICT_FLAG = "--strict"
STRICT_EXIT = 3


@app.callback()
def _root(strict: bool = typer.Option(False, STRICT_FLAG, help="Exit with code 3 when the run gave any "
                                      "warning (the flag may stand anywhere on the command line).")
          ) -> None:
    """Measure how well a depth camera measures depth over distance x inclination."""


def _say_warnings(found: list[RunWarning]) -> None:
    if not found:
        return
    typer.echo(f"depthstation: {len(found)} warning{'s' if len(found) > 1 else ''}:", err=True)
    for w in found:
        typer.echo(f"depthstation: warning: {w.line()}", err=True)


def main() -> None:
    """Entry point: one-line errors on stderr, exit 2 for bad input, 1 for other failures, 3 for
    warnings under --strict; every warning of the run is printed at the end, one line each.

    The objects the imports made (modules, functions: ~94 k, alive until the exit) are frozen out
    of the cyclic garbage collector: its last pass at the interpreter's exit no longer walks them
    (0.57-0.67 s -> 0.22-0.30 s after `evaluate checkerboard`), nor do the passes during the run."""
    gc.freeze()
    code = run_cli(sys.argv[1:])
    gc.freeze()  # and what the command's own imports made (its module loads when it runs): 0.9x CPU
    if code:
        sys.exit(code)


def run_cli(argv: list[str]) -> int:
    """The console script without the process exit: its exit code (tests call it in-process)."""
    strict = STRICT_FLAG in argv
    args = [a for a in argv if a != STRICT_FLAG]
    token = COMMAND_LINE.set(["depthstation", *argv])
    try:
        with collecting() as found:
            code = _run(args)
    finally:
        COMMAND_LINE.reset(token)
    _say_warnings(found)
    if code == 0 and strict and found:
        typer.echo(f"depthstation: {len(found)} warning(s) and --strict: exit {STRICT_EXIT}", err=True)
        code = STRICT_EXIT
    return code


def _run(args: list[str]) -> int:
    """Run the command; its exit code (errors said in one line)."""
    try:
        rc = app(args=args, standalone_mode=False, prog_name="depthstation")
    except DepthstationError as exc:
        typer.echo(f"depthstation: error: {exc}", err=True)
        return exc.exit_code
    except KeyboardInterrupt as exc:  # a failure held behind the Ctrl-C is said too
        cause = f" ({exc.__cause__})" if exc.__cause__ is not None else ""
        typer.echo(f"depthstation: interrupted{cause}", err=True)
        return 130
    except _EXIT as exc:
        return int(getattr(exc, "exit_code", 0) or 0)
    except _ABORT:
        typer.echo("depthstation: aborted", err=True)
        return 1
    except _USAGE as exc:  # unknown command, missing or invalid option: usage line, exit 2
        if getattr(exc, "ctx", True) is None:  # raised before a command context existed
            words = [w for w in args[:2] if not w.startswith("-")]
            cmd = " ".join(["depthstation", *words])
            typer.echo(f"Usage: {cmd} [OPTIONS] ...\nTry '{cmd} --help' for help.\n", err=True)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            typer.echo(f"depthstation: error: {exc}", err=True)
        code = getattr(exc, "exit_code", 2)
        return code if isinstance(code, int) and code else 2
    except OSError as exc:
        err = disk_error(exc, Path(exc.filename or "."))
        if isinstance(err, DepthstationError):
            typer.echo(f"depthstation: error: {err}", err=True)
            return 1
        typer.echo(f"depthstation: error: {exc.filename or ''}: {exc.strerror or exc}", err=True)
        return 1
    except Exception as exc:  # anything unexpected
        typer.echo(f"depthstation: internal error: {type(exc).__name__}: {exc}", err=True)
        return 1
    if isinstance(rc, int) and rc:
        # click returns the code of an Abort (130 on Ctrl-C) or ctx.exit(n) instead of raising
        if rc == 130:
            typer.echo("depthstation: interrupted", err=True)
        return rc
    return 0


if __name__ == "__main__":
    main()
