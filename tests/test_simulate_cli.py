"""The `depthstation simulate` commands through the console script (exit codes) and the scan output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXE = Path(sys.executable).with_name("depthstation")


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(EXE), "simulate", *args], capture_output=True, text=True, timeout=120)


def test_checkerboard_command_and_errors(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    r = _run("checkerboard", "--protocol", "demo-d455", "--out", str(out), "--frames", "1",
             "--standpoint", "standpoint_04", "--seed", "2")
    assert r.returncode == 0, r.stderr
    names = {p.name for p in out.iterdir()}
    assert {"session.json", "standpoint_04.mcap", "truth.json", "result.json"} <= names
    truth = json.loads((out / "truth.json").read_text())
    assert truth["standpoints"][0]["inclination_deg"] == pytest.approx(35.0)
    r = _run("checkerboard", "--protocol", "demo-d455", "--out", str(out), "--frames", "1")
    assert r.returncode == 2 and "never overwrite" in r.stderr and "Traceback" not in r.stderr
    r = _run("checkerboard", "--model", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "model not found" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\npreset = "d455"\n[effects.disparity_noise]\nsigma = 0.1\n')
    r = _run("checkerboard", "--model", str(bad), "--out", str(tmp_path / "y"))
    assert r.returncode == 2 and "unknown parameter" in r.stderr


def test_scan_writes_sequence_trajectory_and_mesh(tmp_path: Path) -> None:
    from depthstation.core.camera_model import deproject
    from depthstation.core.capture.registry import open_inputs
    from depthstation.simulate.poses import read_tum
    from depthstation.simulate.scene import mesh_scene

    out = tmp_path / "scan"
    r = _run("scan", "--scene", "room", "--trajectory", "walk", "--out", str(out), "--frames", "3",
             "--width", "320", "--height", "240")
    assert r.returncode == 0, r.stderr
    stamps, poses = read_tum(out / "trajectory.txt")
    assert len(poses) == 3 and np.allclose(np.diff(stamps), 1 / 30, atol=1e-6)
    (rec,) = open_inputs([out])
    frames = list(rec.frames())
    assert len(frames) == 3
    np.testing.assert_allclose([f.timestamp_ns / 1e9 for f in frames], stamps, atol=1e-6)
    # the measured depth, put into the world with the true pose, lies on the reference mesh
    import open3d as o3d

    mesh = mesh_scene(out / "scene.ply")
    rc = mesh.raycasting_scene()
    f = frames[1]
    z = f.depth_m(rec.info.depth_units_m)
    v, u = np.nonzero(np.isfinite(z))
    pts = deproject(rec.info.depth_intrinsics, u, v, z[v, u])
    world = pts @ poses[1][:3, :3].T + poses[1][:3, 3]
    dist = rc.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
    assert np.median(dist) < 0.02  # within the sensor noise at room scale
