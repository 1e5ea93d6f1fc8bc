"""Installs where users are: the evaluation stack imports and runs with pyrealsense2 absent (macOS,
Jetson: the [camera] extra installs nothing there), the live path says in one line how to get it,
TOML reads through tomli where the standard tomllib is missing (Python 3.10), and usage errors
exit 2 with the usage line."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# A meta-path finder that makes the named top-level modules unimportable, as on a machine
# without them; the stack is then imported and run in a fresh interpreter.
HIDE = textwrap.dedent("""
    import sys
    class _Hide:
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in {hidden!r}:
                raise ModuleNotFoundError(f"No module named {{name!r}}")
            return None
    sys.meta_path.insert(0, _Hide())
    for _m in list(sys.modules):
        if _m.split('.')[0] in {hidden!r}:
            del sys.modules[_m]
""")


def _run(hidden: set[str], code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    script = HIDE.format(hidden=hidden) + textwrap.dedent(code)
    return subprocess.run([sys.executable, "-c", script], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_evaluation_stack_without_pyrealsense2(tmp_path: Path) -> None:
    res = _run({"pyrealsense2"}, """
        import importlib, sys
        import depthstation.app.cli as cli            # every stage's commands
        for name in ("depthstation.evaluate.checkerboard.run", "depthstation.evaluate.scan.run",
                     "depthstation.evaluate.explain.run", "depthstation.simulate.checkerboard_session",
                     "depthstation.core.capture.registry", "depthstation.core.capture.export"):
            importlib.import_module(name)
        assert "pyrealsense2" not in sys.modules
        from depthstation.core.capture.sample_recordings import sample_frames, sample_info
        from depthstation.core.capture.mcap_writer import write_mcap
        from depthstation.core.capture.registry import open_recording
        info = sample_info()
        write_mcap("x.mcap", info, sample_frames(info, 2))
        assert open_recording("x.mcap").frame_count == 2
        sys.argv = ["depthstation", "simulate", "model", "d455"]
        cli.main()
        print("STACK-OK")
        sys.argv = ["depthstation", "acquire", "session", "--camera", "live", "--protocol", "demo-d455",
                    "--session", "s"]
        cli.main()
    """, tmp_path)
    assert "STACK-OK" in res.stdout, res.stderr
    assert res.returncode == 1, res.stderr  # the live path: a camera error, not an internal one
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[camera]'" in err[0] and "Traceback" not in res.stderr


def test_toml_through_tomli_without_tomllib(tmp_path: Path) -> None:
    """Python 3.10 has no tomllib: boards, protocols and models read through tomli."""
    pytest.importorskip("tomli")
    res = _run({"tomllib"}, """
        import sys
        from depthstation.core.tomlcompat import tomllib
        assert tomllib.__name__ == "tomli", tomllib.__name__
        from depthstation.core.protocol import load_protocol
        from depthstation.simulate.model import load_model
        p = load_protocol("demo-d455")
        assert p.board.squares_x == 7 and load_model("d455-ideal").camera.baseline_m > 0
        open("bad.toml", "w").write("[board\\n")
        from depthstation.core.errors import InputError
        try:
            load_protocol("bad.toml")
        except InputError as exc:
            print("ERR", exc)
        print("TOMLI-OK")
    """, tmp_path)
    assert "TOMLI-OK" in res.stdout, res.stderr
    assert "ERR bad.toml" in res.stdout


def test_usage_errors_exit_2_with_the_usage_line(capsys: pytest.CaptureFixture[str]) -> None:
    from depthstation.app import cli

    for args in (["nosuchcommand"], ["evaluate", "checkerboard"], ["capture", "info", "--bogus", "x"],
                 ["evaluate", "checkerboard", "x", "--board", "b", "--out", "o", "--frames", "abc"],
                 ["evaluate", "scan", "--sequence"]):
        old = sys.argv
        sys.argv = ["depthstation", *args]
        try:
            with pytest.raises(SystemExit) as done:
                cli.main()
        finally:
            sys.argv = old
        err = capsys.readouterr().err
        assert done.value.code == 2, args
        assert "Usage: depthstation" in err and "internal error" not in err and "Error:" in err, args
