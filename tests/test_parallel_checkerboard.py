"""The checkerboard study with standpoints as tasks: the table from 2 local processes and from a
2-worker Dask LocalCluster equals the single-process table (real D435 ChArUco standpoint)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from depthstation.core.board import Board
from depthstation.core.capture.registry import open_inputs
from depthstation.core.parallel import ChunkRunner
from depthstation.evaluate.checkerboard.chunks import StandpointOptions, run_standpoints


def run_checkerboard(inputs: list[Path], board: Board, *, frames: int, workers: int = 1,
                     cluster: str | None = None) -> list[Any]:
    with ChunkRunner(workers, cluster) as runner:
        return run_standpoints(open_inputs(inputs), board, StandpointOptions(frames=frames), runner)


@pytest.fixture(scope="module")
def standpoints(charuco_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three standpoints (links to the one real standpoint folder under other names)."""
    root = tmp_path_factory.mktemp("cb")
    (root / "camera.json").symlink_to(charuco_dir / "camera.json")
    out = []
    for name in ("pose_a", "pose_b", "pose_c"):
        link = root / name
        link.symlink_to(charuco_dir / "pose03", target_is_directory=True)
        out.append(link)
    return out


def rows(results: list[Any]) -> list[dict[str, Any]]:
    return [r.row() for r in results]


def assert_same_rows(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> None:
    assert [r["standpoint"] for r in a] == [r["standpoint"] for r in b]
    for ra, rb in zip(a, b, strict=True):
        assert ra.keys() == rb.keys()
        for k, va in ra.items():
            vb = rb[k]
            if isinstance(va, float) and math.isnan(va):
                assert isinstance(vb, float) and math.isnan(vb), k
            elif isinstance(va, float):
                assert va == pytest.approx(vb, rel=1e-12, abs=1e-15), k
            else:
                assert va == vb, k


def test_checkerboard_table_equal_on_all_paths(standpoints: list[Path], charuco_dir: Path) -> None:
    distributed = pytest.importorskip("distributed")
    from depthstation.core.protocol import load_board

    board = load_board(charuco_dir / "board.json")
    serial = rows(run_checkerboard(standpoints, board, frames=3))
    assert [r["standpoint"] for r in serial] == ["pose_a", "pose_b", "pose_c"]
    assert all(r["frames"] == 3 for r in serial)
    assert_same_rows(serial, rows(run_checkerboard(standpoints, board, frames=3, workers=2)))
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as lc:
        on_dask = rows(run_checkerboard(standpoints, board, frames=3, cluster=lc.scheduler_address))
    assert_same_rows(serial, on_dask)
