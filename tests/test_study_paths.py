"""One way to run a study: a batch item and the command write the same result folder.

The same files (tables, grid, summary, figures), the same table and grid contents, the same
summary but for its timings, the same result.json but for its creation time and the parameters
only the command line carries (rerun target, workers).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_batch_kinds import make_scan_item

from depthstation.core.grid import GRID_FILE, Grid
from depthstation.core.run_warnings import collecting
from depthstation.evaluate.batch import batch
from depthstation.evaluate.checkerboard.run import run_checkerboard
from depthstation.evaluate.scan.run import ScanOptions, run_scan

pytest.importorskip("open3d")


def files(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if not p.name.startswith(".")}


def without(d: dict[str, Any], *keys: str) -> dict[str, Any]:
    return {k: v for k, v in d.items() if k not in keys}


def test_checkerboard_item_and_command_write_the_same_folder(tmp_path: Path, charuco_dir: Path) -> None:
    inputs = [charuco_dir / "pose03", charuco_dir / "pose05"]
    board = charuco_dir / "board.json"
    command = tmp_path / "command"
    with collecting():  # as the console script runs every command: result.json lists the warnings
        run_checkerboard(inputs, board, command, frames=2)
    items = ", ".join(f'"{p}"' for p in inputs)
    (tmp_path / "m.toml").write_text(
        f'out = "b"\n[[items]]\nkind = "checkerboard"\nname = "cb"\n'
        f'inputs = {{ inputs = [{items}], board = "{board}" }}\noptions = {{ frames = 2 }}\n')
    with collecting():
        batch(tmp_path / "m.toml")
    item = tmp_path / "b" / "cb"
    assert files(item) == files(command)
    for name in ("standpoints.csv", "frames.csv"):
        assert (item / name).read_text() == (command / name).read_text(), name
    sa, sb = (json.loads((f / "summary.json").read_text()) for f in (item, command))
    assert sa == sb
    ra, rb = (json.loads((f / "result.json").read_text()) for f in (item, command))
    assert without(ra, "created") == without(rb, "created")


def test_scan_item_and_command_write_the_same_folder(tmp_path: Path) -> None:
    inp = make_scan_item(tmp_path, "room", 5)
    options = {"icp": False, "chunk_frames": 2, "distance_bin_m": 0.05, "inclination_bin_deg": 1.0,
               "min_count_sequence": 20}
    command = tmp_path / "command"
    with collecting():
        run_scan(inp["sequence"], inp["poses"], inp["reference"], command,
                 ScanOptions(similarity=inp["similarity"], **options))  # type: ignore[arg-type]
    fields = ", ".join(f'{k} = "{v}"' for k, v in inp.items())
    opts = ", ".join(f"{k} = {str(v).lower() if isinstance(v, bool) else v}" for k, v in options.items())
    (tmp_path / "m.toml").write_text(
        f'out = "b"\n[[items]]\nkind = "scan"\nname = "room"\ninputs = {{ {fields} }}\n'
        f"options = {{ {opts} }}\n")
    with collecting():
        batch(tmp_path / "m.toml")
    item = tmp_path / "b" / "room"
    assert files(item) == files(command)
    a, b = Grid.load(item / GRID_FILE), Grid.load(command / GRID_FILE)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.m2, b.m2)
    sa, sb = (json.loads((f / "summary.json").read_text()) for f in (item, command))
    assert sa["grid"]["samples"] > 1000

    def same(s: dict[str, Any], out: Path) -> dict[str, Any]:
        s = without(s, "timing_s")
        s["reference_mesh"] = without(s["reference_mesh"], "path")
        s["figures"] = {k: Path(v).name for k, v in s["figures"].items()}
        return s

    assert same(sa, item) == same(sb, command)
    ra, rb = (json.loads((f / "result.json").read_text()) for f in (item, command))
    cli_only = ("rrd", "workers", "cluster")
    assert without(ra["parameters"], *cli_only) == without(rb["parameters"], *cli_only)
