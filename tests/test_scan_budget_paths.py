"""`evaluate scan --budget` on every path a study runs: one process, a Dask LocalCluster, and a
batch item on two local processes. The refinement's per-frame work (read, subsample, ray cast,
linearise) goes to the workers with the study's chunks; its solve couples the frames and runs in
the command's process. Each path must give the one process's budget: the same corrections, the
same sensor grid, the same budget.json (but for its timings).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_scan_budget import make_case

from depthstation.core.grid import Grid
from depthstation.evaluate.batch import batch
from depthstation.evaluate.scan import budget_frames
from depthstation.evaluate.scan.run import ScanOptions, run_scan

FRAMES = 40
CHUNK = 8  # five chunks of frames: the workers share them


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return make_case(tmp_path_factory.mktemp("budget_paths"), perturb=True, seed=11, frames=FRAMES)


def inputs(case: dict[str, Any]) -> tuple[Path, Path, Path]:
    root = case["root"]
    return root / "sequence.mcap", root / "trajectory.txt", root / "room.ply"


@pytest.fixture(scope="module")
def one_process(case: dict[str, Any]) -> Path:
    out = case["root"] / "one"
    run_scan(*inputs(case), out, ScanOptions(budget=True, chunk_frames=CHUNK))
    return out


def same(a: Any, b: Any, where: str = "budget") -> None:
    """Equal JSON values, numbers to 1e-9 relative (a study's grid merged in another order may
    differ in its last bits; the corrections themselves are equal)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and not isinstance(a, bool):
        assert isinstance(b, float) and math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12), (where, a, b)
    else:
        assert a == b, (where, a, b)


def assert_same_budget(a: Path, b: Path) -> None:
    ja, jb = (json.loads((d / "budget.json").read_text()) for d in (a, b))
    ja.pop("timing_s")
    jb.pop("timing_s")
    assert ja["pose_refinement"]["frames"] == FRAMES
    same(ja, jb)
    ca, cb = (np.loadtxt(d / "pose_corrections.csv", delimiter=",", skiprows=1) for d in (a, b))
    np.testing.assert_array_equal(ca, cb)
    assert np.abs(ca[:, 5:8]).max() > 0.003  # the walk's perturbation was corrected, not left at zero
    ga, gb = Grid.load(a / "sensor_grid.npz"), Grid.load(b / "sensor_grid.npz")
    assert int(ga.count.sum()) > 0
    np.testing.assert_array_equal(ga.count, gb.count)
    np.testing.assert_allclose(ga.mean_m, gb.mean_m, rtol=0, atol=1e-12, equal_nan=True)


def test_budget_on_a_dask_cluster_equals_one_process(case: dict[str, Any], one_process: Path) -> None:
    distributed = pytest.importorskip("distributed")
    out = case["root"] / "dask"
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        run_scan(*inputs(case), out, ScanOptions(budget=True, chunk_frames=CHUNK,
                                                 cluster=cluster.scheduler_address))
        with distributed.Client(cluster.scheduler_address) as client:
            cast_there = client.run(lambda: budget_frames._CACHE.caster is not None)
    # the refinement's frames were ray cast on the workers, not in this process
    assert cast_there and all(cast_there.values()), cast_there
    assert_same_budget(one_process, out)


def test_a_batch_item_with_budget_writes_the_commands_budget(case: dict[str, Any], one_process: Path) -> None:
    """`budget = true` in a scan item's options: the item's folder holds the budget the command
    writes (on two local processes here), and the combined grid is still the study's grid.npz."""
    root = case["root"]
    seq, poses, mesh = inputs(case)
    manifest = root / "campaign.toml"
    manifest.write_text(f'out = "campaign"\n[[items]]\nkind = "scan"\nname = "walk"\n'
                        f'inputs = {{ sequence = "{seq.name}", poses = "{poses.name}", '
                        f'reference = "{mesh.name}" }}\n'
                        f"options = {{ budget = true, chunk_frames = {CHUNK} }}\n")
    report = batch(manifest, workers=2)
    assert report.done == ["walk"]
    item = root / "campaign" / "walk"
    assert_same_budget(one_process, item)
    combined = Grid.load(root / "campaign" / "combined" / "grid.npz")
    np.testing.assert_array_equal(combined.count, Grid.load(item / "grid.npz").count)
