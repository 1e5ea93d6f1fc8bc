"""explain's inputs in the open world: mixed cameras, short standpoints, missing calibration, models
that disagree with the recording, and bad options, each refused or warned in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from depthstation.app.cli import run_cli

PROTOCOL = """name = "small"
description = "small"
[board]
type = "checkerboard"
squares_x = 7
squares_y = 5
square_length_m = 0.095
[streams]
width = {width}
height = {height}
fps = 30
[plan]
frames_per_standpoint = 3
start_distance_m = 1.0
step_m = 0.5
max_distance_m = 1.5
inclinations_deg = [0.0]
"""


def _protocol(root: Path, width: int = 320, height: int = 180) -> Path:
    p = root / f"p_{width}.toml"
    p.write_text(PROTOCOL.format(width=width, height=height))
    return p


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 320x180 standpoints of 3 frames (1.0 and 1.5 m); `p_320.toml` beside them is the board."""
    root = tmp_path_factory.mktemp("small")
    assert run_cli(["simulate", "checkerboard", "-p", str(_protocol(root)), "--out", str(root / "s"),
                    "--seed", "1"]) == 0
    return root


def _explain(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    capsys.readouterr()
    code = run_cli(["explain", *args])
    return code, capsys.readouterr().err


def test_mixed_resolutions_refused(small: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 640x360 standpoint among 320x180 ones would be simulated at 320x180: refused, each camera's
    standpoints named."""
    big = tmp_path / "big"
    assert run_cli(["simulate", "checkerboard", "-p", str(_protocol(tmp_path, 640, 360)), "--out", str(big),
                    "--standpoint", "standpoint_02"]) == 0
    (big / "standpoint_02.mcap").rename(big / "far.mcap")
    code, err = _explain(capsys, str(small / "s" / "standpoint_01.mcap"), str(big / "far.mcap"),
                         "--board", str(small / "p_320.toml"), "--out", str(tmp_path / "e"))
    assert code == 2, err
    assert "more than one camera" in err and "standpoint_01: depth 320x180" in err and "far: depth 640x360" in err
    assert "Traceback" not in err and not (tmp_path / "e").exists()
