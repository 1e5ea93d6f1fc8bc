"""A cloud reference measured against its points (evaluate/scan/point_reference.py): a sparse, holed,
noisy TLS scan of the synthetic room (one standpoint on a 1074 x 345 angular grid, written as a
binary PLY by numpy here, not by the reader) gives the grid of the true surface."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from depthstation.core.capture.mcap_writer import write_mcap
from depthstation.core.errors import InputError
from depthstation.core.grid import Grid
from depthstation.core.parallel import ChunkRunner
from depthstation.evaluate.scan.point_reference import OK, ROUGH, SPARSE, PointParams, fit_triangles
from depthstation.evaluate.scan.reference import unmeasured_file
from depthstation.evaluate.scan.run import ScanOptions, prepare_scan, run_prepared, run_scan
from depthstation.evaluate.scan.synthetic import ErrorModel, Room, make_sequence
from depthstation.evaluate.scan.trajectory import write_tum

STATION = (1.4, 1.3, 1.6)
HOLES = [((0.0, 2.0, 1.5), 0.35), ((6.0, 1.0, 1.0), 0.3), ((3.0, 5.0, 2.0), 0.4), ((2.0, 4.0, 0.0), 0.3),
         ((4.5, 1.0, 2.8), 0.3)]
TLS_NOISE_M = 0.0015


def tls_scan(room: Room, origin: tuple[float, float, float], rng: np.random.Generator, n_az: int = 1074,
             n_el: int = 345) -> np.ndarray:
    """A TLS standpoint: rays on an azimuth x elevation grid (-65 to 90 deg), range noise along the beam,
    5 % dropouts and discs of surface without returns (holes)."""
    az = np.radians(np.arange(n_az) * 360.0 / n_az)
    el = np.radians(np.linspace(-65.0, 90.0, n_el))
    a, e = np.meshgrid(az, el)
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    t, _ = room.intersect(np.asarray(origin, float), d)
    ok = np.isfinite(t)
    pts = np.asarray(origin) + (t[ok] + rng.normal(0.0, TLS_NOISE_M, ok.sum()))[:, None] * d[ok]
    keep = rng.random(len(pts)) > 0.05
    for c, r in HOLES:
        keep &= np.linalg.norm(pts - np.asarray(c), axis=1) > r
    return np.asarray(pts[keep])


def write_ply_points(path: Path, pts: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty double x\n"
              "property double y\nproperty double z\nend_header\n")
    path.write_bytes(header.encode() + np.ascontiguousarray(pts, "<f8").tobytes())


@pytest.fixture(scope="module")
def scan(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    o3d = pytest.importorskip("open3d")
    root = tmp_path_factory.mktemp("points")
    rng = np.random.default_rng(1)
    room = Room()
    write_ply_points(root / "cloud.ply", tls_scan(room, STATION, rng))
    # the D455-like noise, a bias in inclination only (a cell's mean does not move with its pixels' depths)
    seq = make_sequence(frames=16, width=160, height=120, seed=3, model=ErrorModel(a_per_m=0.0))
    write_mcap(root / "seq.mcap", seq.info, seq.frames())
    write_tum(root / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    np.savetxt(root / "identity.txt", np.eye(4))
    o3d.io.write_triangle_mesh(str(root / "room.ply"), room.mesh(segments=256))
    return {"root": root}


def _study(root: Path, reference: Path, name: str, mode: str = "points") -> Any:
    opt = ScanOptions(similarity=root / "identity.txt", distance_bin_m=0.25, inclination_bin_deg=5.0,
                      min_count_sequence=20, poisson_depth=8, reference_mode=mode)
    with ChunkRunner(1) as runner:
        job = prepare_scan(root / "seq.mcap", root / "poses.txt", reference, root / name, opt)
        return job, run_prepared(job, runner)


@pytest.mark.slow  # a 0.35 M point scan meshed (Poisson depth 8) and fitted: ~30 s of CPU
def test_the_grid_against_a_sparse_holed_cloud_is_the_true_surface_s(scan: dict[str, Any]) -> None:
    root: Path = scan["root"]
    _, truth = _study(root, root / "room.ply", "truth")
    job, points = _study(root, root / "cloud.ply", "points")
    a, b = truth.grid, points.grid
    both = (a.count >= 200) & (b.count >= 200)
    assert both.sum() >= 40
    # means where both cells' own sampling uncertainty is below half the tolerance
    sampled = both & (a.u95_m <= 0.0005) & (Grid(b.distance_edges_m, b.inclination_edges_deg, b.count, b.mean,
                                                  b.m2, b.moments).u95_m <= 0.0005)
    assert sampled.sum() >= 20
    diff = np.abs(a.mean - b.mean)[sampled]
    assert diff.max() <= 0.001, np.sort(diff)[-5:]
    ratio = (b.std / a.std)[both]
    assert ratio.max() <= 1.25 and ratio.min() >= 1 / 1.25, (ratio.min(), ratio.max())
    # the pixels left out are counted by reason, and add up to the ones the pass left out
    px = points.summary()["pixels"]
    reasons = [px[f"reference_{r}"] for r in ("sparse", "rough", "mesh_off", "edge")]
    assert min(reasons[:2]) > 0 and sum(reasons) == px["unmeasured_surface"]
    fits = job.mesh_info["point_fits"]
    assert fits["supported"] > 0.5 * fits["triangles"]
    # the reference's own uncertainty: about the TLS noise over sqrt(16 points), carried per cell
    u = points.reference_u.u_m()[sampled]
    assert np.all(np.isfinite(u)) and 0.2 * TLS_NOISE_M / 4 < np.median(u) < 3 * TLS_NOISE_M / 4
    a.reference_u_m = None
    b.reference_u_m = points.reference_u.u_m()
    assert np.all(b.u95_m[sampled] > 1.96 * b.reference_u_m[sampled])
    assert np.all(diff <= a.u95_m[sampled] + b.u95_m[sampled])
    # the same cloud through its Poisson mesh alone (`--reference-mode mesh` on the same mesh) is
    # worse: what the point path is for
    job.config = replace(job.config, point_fits=None,
                         unmeasured=unmeasured_file(job.mesh_path, job.mesh_info))
    with ChunkRunner(1) as runner:
        m = run_prepared(job, runner).grid
    assert np.abs(a.mean - m.mean)[sampled & (m.count >= 200)].max() > diff.max()


def test_fits_tell_holes_and_edges_from_surface() -> None:
    """A plane sampled at 1 cm with 1 mm noise and a hole, meshed by a fine grid of triangles, and a
    corner: the plane is fitted within its noise / sqrt(n), the hole and the corner are left out."""
    rng = np.random.default_rng(0)
    g = np.arange(0.0, 1.0, 0.01)
    x, y = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), y.ravel(), rng.normal(0, 0.001, x.size)], -1)
    pts = pts[np.hypot(pts[:, 0] - 0.5, pts[:, 1] - 0.5) > 0.15]
    wy, wz = np.meshgrid(np.arange(0.25, 0.75, 0.01), np.arange(0.01, 0.51, 0.01))
    wall = np.stack([np.zeros(wy.size), wy.ravel(), wz.ravel()], -1)  # a wall at x = 0 on the plane's edge
    cloud = np.concatenate([pts, wall])
    s = np.arange(0.02, 0.99, 0.02)
    cx, cy = np.meshgrid(s, s)
    centres = np.stack([cx.ravel(), cy.ravel(), np.zeros(cx.size)], -1)
    v = np.concatenate([centres + np.array(off) for off in ((-0.005, -0.005, 0), (0.005, -0.005, 0),
                                                              (0, 0.005, 0))])
    n = len(centres)
    tri = np.stack([np.arange(n), np.arange(n) + n, np.arange(n) + 2 * n], -1)
    fits, info = fit_triangles(v, tri, cloud, PointParams())
    r = np.hypot(centres[:, 0] - 0.5, centres[:, 1] - 0.5)
    assert np.all(fits.reason[r < 0.1] == SPARSE)
    # at the corner with the wall: left out as rough, or a plane still the floor's (within 2 mm, 6 deg)
    corner = (centres[:, 0] < 0.05) & (np.abs(centres[:, 1] - 0.5) < 0.2)
    kept = corner & (fits.reason == OK)
    assert np.all(fits.reason[corner & ~kept] == ROUGH)
    nk, ck = fits.normal[kept], centres[kept]
    height = (fits.offset[kept] - nk[:, 0] * ck[:, 0] - nk[:, 1] * ck[:, 1]) / nk[:, 2]  # at the triangle
    assert np.all(np.abs(height) < 0.002)
    assert np.all(np.abs(fits.normal[kept, 2]) > np.cos(np.radians(6.0)))
    inner = (r > 0.2) & (np.abs(centres[:, :2] - 0.5) < 0.4).all(axis=1)
    assert np.mean(fits.reason[inner] == OK) > 0.98
    ok = inner & (fits.reason == OK)
    no, co = fits.normal[ok], centres[ok]
    z0 = (fits.offset[ok] - no[:, 0] * co[:, 0] - no[:, 1] * co[:, 1]) / no[:, 2]
    assert np.median(np.abs(z0)) < 3 * 0.001 / 4  # z = 0 at the triangle, within noise / sqrt(16)
    assert 0.5 * 0.001 / 4 < np.median(fits.sigma[ok]) < 2 * 0.001 / 4
    assert 0.0007 < info["noise_floor_m"] < 0.0013


def test_a_random_cloud_is_a_one_line_error_naming_it(tmp_path: Path) -> None:
    pytest.importorskip("open3d")
    rng = np.random.default_rng(0)
    write_ply_points(tmp_path / "random.ply", rng.uniform(0.0, 6.0, (4000, 3)))
    seq = make_sequence(frames=3, width=40, height=30)
    write_mcap(tmp_path / "seq.mcap", seq.info, seq.frames())
    write_tum(tmp_path / "poses.txt", np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    run = subprocess.run([sys.executable, "-m", "depthstation.app.cli", "evaluate", "scan",
                          "--sequence", str(tmp_path / "seq.mcap"), "--poses", str(tmp_path / "poses.txt"),
                          "--reference", str(tmp_path / "random.ply"), "--out", str(tmp_path / "out"),
                          "--poisson-depth", "6"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "Traceback" not in run.stderr and "no triangles" not in run.stderr
    assert any("random.ply" in ln and "error" in ln.lower() for ln in run.stderr.splitlines()), run.stderr
    # the mesh path (in this process: its error is the same kind, naming the file)
    opt = ScanOptions(poisson_depth=6, reference_mode="mesh")
    with pytest.raises(InputError, match=r"random\.ply"):
        run_scan(tmp_path / "seq.mcap", tmp_path / "poses.txt", tmp_path / "random.ply", tmp_path / "mesh",
                 opt)
