"""The reference-scan study in chunks: serial, 2 local processes and a 2-worker Dask LocalCluster
give the grid of the one-pass evaluation (to float rounding), also when a worker is killed."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("open3d")
from depthstation.core.parallel import ChunkRunner
from depthstation.evaluate.scan import chunks as chunks_mod
from depthstation.evaluate.scan.chunks import ScanChunk, run_scan_chunks, scan_chunk


def run_scan(sequence: Path, mesh: Path, trajectory: Any, config: Any, *, chunk_frames: int = 64,
             workers: int = 1, cluster: str | None = None) -> Any:
    with ChunkRunner(workers, cluster) as runner:
        return run_scan_chunks(sequence, mesh, trajectory, config, runner, chunk_frames=chunk_frames)


@pytest.fixture(scope="module")
def scan_case(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    import open3d as o3d

    from depthstation.evaluate.scan.study import StudyConfig
    from depthstation.evaluate.scan.synthetic import Room, make_sequence, write_tum_folder
    from depthstation.evaluate.scan.trajectory import Trajectory

    root = tmp_path_factory.mktemp("scan")
    room = Room()
    seq = make_sequence(frames=10, width=80, height=60, room=room, seed=3)
    folder = write_tum_folder(seq, root / "seq")
    mesh = root / "room.ply"
    o3d.io.write_triangle_mesh(str(mesh), room.mesh(segments=64))  # type: ignore[arg-type]
    traj = Trajectory(np.asarray(seq.timestamps_ns, np.float64) * 1e-9, np.asarray(seq.poses))
    config = StudyConfig(distance_bin_m=0.05, inclination_bin_deg=1.0, nthreads=1)
    return {"sequence": folder, "mesh": mesh, "trajectory": traj, "config": config}


@pytest.fixture(scope="module")
def one_pass(scan_case: dict[str, Any]) -> Any:
    """The scan helper's own single-process evaluation, all frames in one chunk."""
    return run_scan(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"], scan_case["config"],
                    chunk_frames=10**6)


def assert_same(a: Any, b: Any) -> None:
    np.testing.assert_array_equal(a.grid.count, b.grid.count)
    np.testing.assert_allclose(a.grid.mean, b.grid.mean, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(a.grid.m2, b.grid.m2, rtol=1e-8, atol=1e-18)
    np.testing.assert_array_equal(a.stats, b.stats)
    assert sorted(a.used) == sorted(b.used)


def killing_scan_chunk(chunk: ScanChunk) -> Any:
    """scan_chunk, but the worker running the second chunk dies once (flag file)."""
    flag = Path(str(chunk.sequence) + ".killed")
    if chunk.start > 0 and chunk.start == chunk.limit and not flag.exists():
        flag.write_text(str(os.getpid()))
        os._exit(21)
    return scan_chunk(chunk)


def test_chunked_scan_equals_one_pass(scan_case: dict[str, Any], one_pass: Any) -> None:
    assert one_pass.grid.total > 10_000
    serial = run_scan(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"],
                      scan_case["config"], chunk_frames=3)
    assert_same(serial, one_pass)
    local = run_scan(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"],
                     scan_case["config"], chunk_frames=3, workers=2)
    assert_same(local, one_pass)
    assert local.used == list(range(10))  # merged in frame order


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=None) as lc:
        yield lc.scheduler_address


def test_scan_on_dask_with_a_killed_worker(scan_case: dict[str, Any], one_pass: Any, cluster: str,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    on_dask = run_scan(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"],
                       scan_case["config"], chunk_frames=3, cluster=cluster)
    assert_same(on_dask, one_pass)
    flag = Path(str(scan_case["sequence"]) + ".killed")
    monkeypatch.setattr(chunks_mod, "scan_chunk", killing_scan_chunk)
    killed = run_scan(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"],
                      scan_case["config"], chunk_frames=3, cluster=cluster)
    assert flag.exists(), "no worker was killed"
    assert_same(killed, one_pass)


def test_scan_chunks_carry_no_pixels(scan_case: dict[str, Any]) -> None:
    import pickle

    chunks = chunks_mod.scan_chunks(scan_case["sequence"], scan_case["mesh"], scan_case["trajectory"],
                                   replace(scan_case["config"]), chunk_frames=4)
    assert [(c.start, c.limit) for c in chunks] == [(0, 4), (4, 4), (8, 2)]
    assert len(pickle.dumps(chunks[0])) < 10 * 1024  # 60x80 depth alone would be 9.6 kB per frame


def test_the_last_two_chunks_taper_to_short_pieces_that_cover_their_frames_once() -> None:
    """The tail of a study is cut so that cores finish together: halving pieces of the last two
    chunks' frames, contiguous, in order, none longer than the chunk, the last ones 8 frames or less."""
    from depthstation.evaluate.scan.chunks import TAPER_FRAMES, split_last
    from depthstation.evaluate.scan.study import StudyConfig
    from depthstation.evaluate.scan.trajectory import Trajectory

    traj = Trajectory(np.array([0.0]), np.eye(4)[None])
    for frames, size in ((1334, 64), (128, 64), (65, 64), (64, 64), (3, 64), (1, 64), (200, 16)):
        whole = [ScanChunk("seq", "mesh", traj, StudyConfig(), s, min(size, frames - s))
                 for s in range(0, frames, size)]
        cut = split_last(whole)
        starts = [c.start for c in cut]
        limits = [c.limit or 0 for c in cut]
        assert starts == [0, *np.cumsum(limits)[:-1].tolist()], (frames, limits)
        assert sum(limits) == frames
        assert max(limits) <= size
        head = max(len(whole) - 2, 0)
        assert cut[:head] == whole[:head]  # only the tail is cut
        if frames >= 2:
            assert limits[-1] <= TAPER_FRAMES and limits[-2:] == sorted(limits[-2:], reverse=True)
    tail = [ScanChunk("s", "m", traj, StudyConfig(), 1216, 64),
            ScanChunk("s", "m", traj, StudyConfig(), 1280, 54)]
    assert [c.limit for c in split_last(tail)] == [59, 30, 15, 7, 7]


def test_a_mesh_rewritten_in_place_is_read_again_by_the_next_study(scan_case: dict[str, Any],
                                                                   one_pass: Any, tmp_path: Path) -> None:
    """The process keeps its prepared renderer for the next study (batch items, the report's figure
    frame); a mesh file rewritten under the same path must not be served from that cache: the
    second study sees a room 0.25 m larger and its errors move by about that."""
    import open3d as o3d

    from depthstation.evaluate.scan.synthetic import Room

    mesh = tmp_path / "room.ply"
    o3d.io.write_triangle_mesh(str(mesh), Room().mesh(segments=64))  # type: ignore[arg-type]
    first = run_scan(scan_case["sequence"], mesh, scan_case["trajectory"], scan_case["config"])
    assert_same(first, one_pass)
    big = Room().mesh(segments=64)
    big.scale(1.1, center=(0.0, 0.0, 0.0))
    st = mesh.stat()
    o3d.io.write_triangle_mesh(str(mesh), big)  # type: ignore[arg-type]
    os.utime(mesh, ns=(st.st_atime_ns, st.st_mtime_ns + 1))  # even within one mtime tick
    second = run_scan(scan_case["sequence"], mesh, scan_case["trajectory"], scan_case["config"])
    assert second.grid.total > 0
    shift = np.average(second.grid.mean, weights=second.grid.count) - np.average(first.grid.mean,
                                                                                  weights=first.grid.count)
    assert shift < -0.05  # reference depths 10 % longer: measured minus reference falls
    chunks_mod.clear_cache()
    again = run_scan(scan_case["sequence"], mesh, scan_case["trajectory"], scan_case["config"])
    assert_same(again, second)



def test_a_sequence_folder_whose_list_is_rewritten_in_place_is_read_again(scan_case: dict[str, Any],
                                                                          tmp_path: Path) -> None:
    """A worker keeps its open sequence for the next chunk, also of the next study (a Dask cluster's
    workers live on). A TUM folder's depth.txt rewritten in place (an editor, a re-export) leaves
    the folder's own time as it was: the worker must not serve the old frame list."""
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(scan_case["sequence"], folder)
    first = scan_chunk(chunks_mod.scan_chunks(folder, scan_case["mesh"], scan_case["trajectory"],
                                              scan_case["config"], chunk_frames=100)[0])
    assert len(first.used) == 10
    listing = folder / "depth.txt"
    lines = listing.read_text().splitlines()
    st = folder.stat()
    with listing.open("r+") as f:  # in place: the folder's entries, and its mtime, stay
        f.write("\n".join([lines[0], *lines[6:]]) + "\n")  # the last 5 frames only
        f.truncate()
    os.utime(folder, ns=(st.st_atime_ns, st.st_mtime_ns))
    chunk = chunks_mod.scan_chunks(folder, scan_case["mesh"], scan_case["trajectory"], scan_case["config"],
                                   chunk_frames=100)[0]
    assert chunk.limit == 5
    second = scan_chunk(chunk)
    chunks_mod.clear_cache()
    fresh = scan_chunk(chunk)
    assert len(second.used) == len(fresh.used) == 5
    assert_same(second, fresh)  # the last five frames, not the first five of the old list
