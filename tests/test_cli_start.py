"""The console script loads a command's module when the command runs, not every stage's at start."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from depthstation.app import cli
from depthstation.app.cli import COMMANDS
from depthstation.evaluate import cli as evaluate_cli

ROOT = Path(__file__).resolve().parents[1]


def _loaded_after(args: list[str]) -> list[str]:
    """The project modules a fresh process holds after running `depthstation ARGS`."""
    code = ("import json, sys\nfrom depthstation.app.cli import run_cli\n"
            f"run_cli({args!r})\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('depthstation'))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return list(json.loads(r.stdout.strip().splitlines()[-1]))


def test_a_command_loads_its_own_stage_only() -> None:
    """`evaluate checkerboard` loads the evaluate stage's commands, not the camera's, the
    simulator's command line, explain, the error model's or the station's (0.8 s of CPU a start)."""
    loaded = _loaded_after(["evaluate", "checkerboard", "--help"])
    assert "depthstation.evaluate.checkerboard.cli" in loaded
    for other in ("depthstation.acquire.cli", "depthstation.simulate.cli", "depthstation.app.capture_cli",
                  "depthstation.app.station_cli", "depthstation.evaluate.explain.cli",
                  "depthstation.evaluate.errormodel.cli"):
        assert other not in loaded, other


def test_help_lists_every_command_in_order(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.run_cli(["--help"]) == 0
    out = capsys.readouterr().out
    rows = [m[1] for line in out.splitlines() if (m := re.match(r"│ (\S+) ", line))]  # not a wrapped line
    named = [r for r in rows if not r.startswith("-")]
    assert named == list(COMMANDS), out
    assert "The checkerboard and reference-scan studies." in out and "A camera's depth error model" in out


@pytest.mark.parametrize(("path", "commands"), [("depthstation/app/cli.py", COMMANDS),
                                                ("evaluate/cli.py", evaluate_cli.COMMANDS)])
def test_every_module_a_command_loads_is_imported_for_the_type_checkers(path: str,
                                                                        commands: dict[str, str]) -> None:
    """The modules a lazy group's commands name are imported at the top of its file (under
    TYPE_CHECKING), so that the layer and cycle checks and mypy see the graph the program has."""
    tree = ast.parse((ROOT / path).read_text())
    guarded = {alias.name for node in ast.walk(tree) if isinstance(node, ast.If)
               and ast.unparse(node.test) == "TYPE_CHECKING"
               for imp in node.body if isinstance(imp, ast.Import) for alias in imp.names}
    assert guarded == {target.partition(":")[0] for target in commands.values()}


def test_each_command_runs_from_its_module(capsys: pytest.CaptureFixture[str]) -> None:
    """Every command of the lazy groups answers --help (its module found, its commands registered)."""
    for words in [[name] for name in COMMANDS] + [["evaluate", name] for name in evaluate_cli.COMMANDS]:
        assert cli.run_cli([*words, "--help"]) == 0, words
        assert "Usage: depthstation " + " ".join(words) in capsys.readouterr().out
