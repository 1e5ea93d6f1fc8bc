"""The evaluate commands as a user runs them: --workers, --cluster, and what their recordings hold."""

from __future__ import annotations

import csv
import subprocess
from pathlib import Path

import pytest

DEPTHSTATION = str(Path(__file__).resolve().parents[1] / ".venv" / "bin" / "depthstation")


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_checkerboard_workers_equal_serial(charuco_dir: Path, tmp_path: Path) -> None:
    inputs = [str(charuco_dir / "pose03"), str(charuco_dir / "pose07")]
    board = str(charuco_dir / "board.json")
    outs = []
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        proc = subprocess.run([DEPTHSTATION, "evaluate", "checkerboard", *inputs, "--board", board,
                               "--out", str(out), "--frames", "2", "--workers", str(workers), "--no-figures"],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        outs.append(_rows(out / "standpoints.csv"))
    serial, parallel = outs
    assert [r["standpoint"] for r in serial] == ["pose03", "pose07"]
    assert [r["standpoint"] for r in parallel] == [r["standpoint"] for r in serial]
    for a, b in zip(serial, parallel, strict=True):
        for key in ("distance_m", "inclination_deg", "noise_m", "accuracy_m", "fill_rate"):
            assert float(b[key]) == pytest.approx(float(a[key]), rel=1e-9, abs=1e-12), key


def test_scan_on_a_dask_cluster_equals_one_process(tmp_path: Path) -> None:
    """`evaluate scan --cluster ADDRESS`: chunks of frames on a loopback LocalCluster, same grid."""
    import numpy as np
    import open3d as o3d

    distributed = pytest.importorskip("distributed")
    from depthstation.evaluate.scan.run import ScanOptions, run_scan
    from depthstation.evaluate.scan.synthetic import Room, make_sequence, write_tum_folder
    from depthstation.evaluate.scan.trajectory import write_tum

    seq = make_sequence(frames=6, width=80, height=60, seed=3)
    write_tum_folder(seq, tmp_path / "seq")
    write_tum(tmp_path / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), Room().mesh(segments=128))
    np.savetxt(tmp_path / "identity.txt", np.eye(4))
    common = {"similarity": tmp_path / "identity.txt", "icp": False, "distance_bin_m": 0.05,
              "inclination_bin_deg": 1.0, "chunk_frames": 2}
    run_scan(tmp_path / "seq", tmp_path / "poses.txt", tmp_path / "room.ply", tmp_path / "one",
             ScanOptions(**common))
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        run_scan(tmp_path / "seq", tmp_path / "poses.txt", tmp_path / "room.ply", tmp_path / "dask",
                 ScanOptions(**common, cluster=cluster.scheduler_address))
    with np.load(tmp_path / "one" / "grid.npz") as a, np.load(tmp_path / "dask" / "grid.npz") as b:
        assert int(a["count"].sum()) > 0
        np.testing.assert_array_equal(a["count"], b["count"])
        np.testing.assert_allclose(a["mean_m"], b["mean_m"], rtol=0, atol=1e-12, equal_nan=True)
        np.testing.assert_allclose(a["var_m2"], b["var_m2"], rtol=1e-9, atol=1e-15, equal_nan=True)


def test_scan_rrd_carries_the_grid_as_named_tensors(tmp_path: Path) -> None:
    """The scan recording holds the final grid as tensors with dimension names, and progress series."""
    import numpy as np
    import open3d as o3d

    from depthstation.core.rerun_bridge import DISTANCE_DIM, INCLINATION_DIM, RerunTarget, read_rrd
    from depthstation.evaluate.scan.run import ScanOptions, run_scan
    from depthstation.evaluate.scan.synthetic import Room, make_sequence, write_tum_folder
    from depthstation.evaluate.scan.trajectory import write_tum

    seq = make_sequence(frames=4, width=80, height=60, seed=4)
    write_tum_folder(seq, tmp_path / "seq")
    write_tum(tmp_path / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), Room().mesh(segments=128))
    np.savetxt(tmp_path / "identity.txt", np.eye(4))
    rrd = tmp_path / "scan.rrd"
    run_scan(tmp_path / "seq", tmp_path / "poses.txt", tmp_path / "room.ply", tmp_path / "out",
             ScanOptions(similarity=tmp_path / "identity.txt", icp=False, distance_bin_m=0.05,
                         inclination_bin_deg=1.0, target=RerunTarget(rrd=rrd)))
    contents = read_rrd(rrd)
    for name in ("tensors/count", "tensors/mean_error_m", "tensors/std_error_m"):
        shape, dims = contents.tensors.get("/" + name) or contents.tensors[name]
        assert shape == (120, 90)
        assert dims == (DISTANCE_DIM, INCLINATION_DIM)
    assert any("pixels/evaluated" in k for k in contents.series)
