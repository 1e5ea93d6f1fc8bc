"""The rasterising reference renderer against Open3D's ray casting (the reference implementation):
same hits, same depths, same triangles and normals, pixel for pixel, and the same study grid."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from depthstation.core import raster as raster_mod
from depthstation.core.camera_model import Intrinsics
from depthstation.core.errors import InputError
from depthstation.core.geometry import look_at
from depthstation.core.lazy_open3d import open3d
from depthstation.core.raster import MeshRaster, arithmetic_report, fill_rays
from depthstation.evaluate.scan.rasterise import MeshRasteriser, make_renderer
from depthstation.evaluate.scan.raycast import MeshCaster
from depthstation.evaluate.scan.study import StudyConfig, evaluate_chunk
from depthstation.evaluate.scan.synthetic import ErrorModel, Room, make_sequence, walk_around_table
from depthstation.evaluate.scan.trajectory import Trajectory

INTR = Intrinsics(160, 120, 101.3, 101.1, 79.6, 60.2)


def _cast(vertices: Any, triangles: Any, intr: Intrinsics, pose: Any) -> dict[str, Any]:
    """Open3D's answer for the rays of one view (built by the rays both renderers use)."""
    from depthstation.core.camera_model import pixel_rays

    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.int32))
    scene.add_triangles(mesh)
    rays = np.empty((intr.width * intr.height, 6), np.float32)
    fill_rays(rays, np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]),
              pixel_rays(intr).reshape(-1, 3))
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    ids = np.where(np.isfinite(t), ans["primitive_ids"].numpy().astype(np.int64), -1)
    return {"t": t, "ids": ids, "normals": ans["primitive_normals"].numpy()}


def _agreement(vertices: Any, triangles: Any, intr: Intrinsics, poses: Any,
               margin_scale: float = 1.0) -> dict[str, float]:
    raster = MeshRaster(vertices, triangles, margin_scale=margin_scale)
    n = intr.width * intr.height
    tot = {"pixels": 0, "hit_agree": 0, "both": 0, "t_equal": 0, "same_triangle_or_normal": 0, "hits": 0}
    worst_dt = 0.0
    for pose in poses:
        ref = _cast(vertices, triangles, intr, pose)
        t, ids, nrm = np.empty(n, np.float32), np.empty(n, np.int32), np.empty((n, 3), np.float32)
        raster.render(intr, pose, t, ids, nrm)
        hit, hit_ref = ids >= 0, ref["ids"] >= 0
        both = hit & hit_ref
        tot["pixels"] += n
        tot["hits"] += int(hit_ref.sum())
        tot["hit_agree"] += int(np.sum(hit == hit_ref))
        tot["both"] += int(both.sum())
        tot["t_equal"] += int(np.sum(t[both] == ref["t"][both]))
        same_normal = np.all(np.abs(nrm[both] - ref["normals"][both]) <= 1e-6, axis=1)
        tot["same_triangle_or_normal"] += int(np.sum((ids[both] == ref["ids"][both]) | same_normal))
        if both.any():
            worst_dt = max(worst_dt, float(np.abs(t[both].astype(np.float64) - ref["t"][both]).max()))
    return {**tot, "max_dt": worst_dt}


def _assert_equal_to_ray_casting(a: dict[str, float]) -> None:
    assert a["hits"] > 0
    assert a["hit_agree"] / a["pixels"] >= 0.9999, a
    assert a["max_dt"] <= 1e-6, a
    assert a["same_triangle_or_normal"] == a["both"], a


def test_the_arithmetic_of_open3d_is_reproduced_on_this_machine() -> None:
    # the calibration scene: random triangles, rays aimed at them from an off-centre origin
    assert arithmetic_report()["bit_exact_share"] == 1.0


def test_full_size_room_equals_ray_casting() -> None:
    """The study's room (6 x 5 x 2.8 m, a 256-segment table) from a walk round the table."""
    room = Room()
    mesh = room.mesh(segments=256, subdivide_walls=2)
    poses = walk_around_table(room, 6, laps=0.9)
    a = _agreement(np.asarray(mesh.vertices), np.asarray(mesh.triangles), INTR, poses)
    _assert_equal_to_ray_casting(a)
    assert a["t_equal"] == a["both"]  # bit for bit


def _thin_grazing_mesh(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A 40 m floor of long slivers (a fan from one far corner) seen at grazing angles, a
    2000-segment column (0.9 mm facets), a jittered wall of 1 cm triangles, and coordinates
    offset by tens of metres, as a site survey's local frame has them."""
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []

    def add(v: np.ndarray, t: np.ndarray) -> None:
        off = sum(len(x) for x in verts)
        verts.append(v)
        tris.append(t + off)

    origin = np.array([31.7, -18.2, 2.05])
    n = 3000  # floor: a fan of slivers from (0, 0) to points along the far edges
    edge = np.concatenate([np.c_[np.linspace(0, 40, n // 2), np.full(n // 2, 40.0)],
                           np.c_[np.full(n // 2, 40.0), np.linspace(40, 0, n // 2)]])
    v = np.vstack([[0.0, 0.0, 0.0], np.c_[edge, np.zeros(n)]]) - [5.0, 5.0, 0.0]
    add(v, np.c_[np.zeros(n - 1, int), np.arange(1, n), np.arange(2, n + 1)])
    seg = 2000  # column, radius 0.3 m, 2.5 m high
    a = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    ring = np.c_[6.0 + 0.3 * np.cos(a), 3.0 + 0.3 * np.sin(a)]
    v = np.vstack([np.c_[ring, np.zeros(seg)], np.c_[ring, np.full(seg, 2.5)]])
    i = np.arange(seg)
    j = (i + 1) % seg
    add(v, np.vstack([np.c_[i, j, seg + j], np.c_[i, seg + j, seg + i]]))
    gx, gz = np.meshgrid(np.linspace(-2, 4, 301), np.linspace(0, 2.5, 126))  # wall at y = 8
    v = np.c_[gx.ravel(), np.full(gx.size, 8.0), gz.ravel()] + rng.normal(0, 0.001, (gx.size, 3))
    k = np.arange(gx.size).reshape(gx.shape)[:-1, :-1].ravel()
    add(v, np.vstack([np.c_[k, k + 1, k + 302], np.c_[k, k + 302, k + 301]]))
    return np.vstack(verts) + origin, np.vstack(tris)


def test_real_scale_mesh_with_thin_and_grazing_triangles_equals_ray_casting() -> None:
    rng = np.random.default_rng(5)
    vertices, triangles = _thin_grazing_mesh(rng)
    origin = np.array([31.7, -18.2, 2.05])
    poses = []
    for k in range(5):
        eye = origin + np.array([1.0 + 0.5 * k, 0.5 * k, 0.02 + 0.3 * k])  # down to 2 cm over the floor
        target = origin + np.array([6.0, 3.0 + 0.7 * k, 0.9])
        poses.append(look_at(eye, target, (0.0, 0.0, 1.0)))
    a = _agreement(vertices, triangles, INTR, poses)
    _assert_equal_to_ray_casting(a)
    # a much wider rounding margin tests more pixels but finds nothing new
    wide = _agreement(vertices, triangles, INTR, poses[:2], margin_scale=50.0)
    narrow = _agreement(vertices, triangles, INTR, poses[:2])
    assert wide == narrow


def test_rays_through_shared_edges_take_ray_castings_triangle() -> None:
    """A plane whose vertices lie on pixel rays: ties between neighbours are resolved as ray
    casting resolves them (those rays are cast), and nothing falls through the seams."""
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.0, 23.0)
    u, v = np.meshgrid(np.arange(0, 64, 4), np.arange(0, 48, 4))
    z = 2.0
    pts = np.c_[((u - 31.0) / 50.0 * z).ravel(), ((v - 23.0) / 50.0 * z).ravel(), np.full(u.size, z)]
    w = u.shape[1]
    k = np.arange(u.size).reshape(u.shape)[:-1, :-1].ravel()
    tris = np.vstack([np.c_[k, k + 1, k + w + 1], np.c_[k, k + w + 1, k + w]])
    raster = MeshRaster(pts, tris)
    a = _agreement(pts, tris, intr, [np.eye(4)])
    assert a["hit_agree"] == a["pixels"] and a["t_equal"] == a["both"]
    ref = _cast(pts, tris, intr, np.eye(4))
    n = intr.width * intr.height
    t, ids = np.empty(n, np.float32), np.empty(n, np.int32)
    raster.render(intr, np.eye(4), t, ids)
    assert raster.stats[3] > 0  # there were ties
    assert np.array_equal(ids, ref["ids"])


def _blocks_in_view(raster: MeshRaster, intr: Intrinsics, pose: Any, whole_clusters: bool = False) -> int:
    """Triangles in the blocks (BLOCK_SIZE) of clusters whose boxes meet the view's frustum (planes
    through the camera centre, 2 px of slack), counted here in the test's own numpy form; with
    `whole_clusters`, all triangles of those clusters."""
    slack = 2.0 / min(intr.fx, intr.fy)
    xlo, xhi = -intr.ppx / intr.fx - slack, (intr.width - 1 - intr.ppx) / intr.fx + slack
    ylo, yhi = -intr.ppy / intr.fy - slack, (intr.height - 1 - intr.ppy) / intr.fy + slack
    normals = np.array([[1, 0, -xlo], [-1, 0, xhi], [0, 1, -ylo], [0, -1, yhi], [0, 0, 1.0]]) @ pose[:3, :3].T
    origin = pose[:3, 3].astype(np.float32).astype(np.float64)

    def inside(lo: Any, hi: Any) -> Any:
        ok = np.ones(lo.shape[:-1], bool)
        for nrm in normals:
            ok &= (np.where(nrm > 0, hi, lo) - origin) @ nrm >= -1e-9
        return ok

    sizes = np.diff(raster.cl_start)
    block = raster_mod.BLOCK_SIZE
    per_block = np.clip(sizes[:, None] - block * np.arange(raster.bl_lo.shape[1]), 0, block)
    keep = inside(raster.cl_lo, raster.cl_hi)[:, None] & (whole_clusters | inside(raster.bl_lo, raster.bl_hi))
    return int(per_block[keep].sum())


def test_blocks_outside_the_view_are_culled_and_the_rest_still_equals_ray_casting() -> None:
    """A 6 x 6 m floor of 1.5 cm triangles, seen from above at a slant, the view's edges cutting its
    clusters (in Morton order, so a cluster's blocks go in and out of the view): only the blocks
    that meet the frustum are bounded, and the depth is still ray casting's, bit for bit."""
    rng = np.random.default_rng(11)
    g = np.linspace(-3.0, 3.0, 401)
    gx, gy = np.meshgrid(g, g)
    pts = np.c_[gx.ravel(), gy.ravel(), rng.normal(0, 0.002, gx.size)]
    w = g.size
    k = np.arange(gx.size).reshape(gx.shape)[:-1, :-1].ravel()
    tris = np.vstack([np.c_[k, k + 1, k + w + 1], np.c_[k, k + w + 1, k + w]])
    poses = [look_at(np.array([0.4, -0.3, 1.6]), np.array([1.1, 0.6, 0.0]), up=(0.3, 1.0, 0.0)),
             look_at(np.array([-1.0, 0.5, 0.9]), np.array([0.0, 0.0, 0.0]))]
    raster = MeshRaster(pts, tris)
    n = INTR.width * INTR.height
    t, ids = np.empty(n, np.float32), np.empty(n, np.int32)
    for pose in poses:
        before = raster.stats.copy()
        raster.render(INTR, pose, t, ids)
        bounded = raster.stats[4] - before[4]
        assert bounded == _blocks_in_view(raster, INTR, pose)
        assert bounded < _blocks_in_view(raster, INTR, pose, whole_clusters=True)  # blocks were culled
        ref = _cast(pts, tris, INTR, pose)
        assert np.array_equal(t, ref["t"]) and np.array_equal(ids, ref["ids"])


def test_a_mesh_with_every_face_twice_ties_everywhere_and_still_equals_ray_casting() -> None:
    """Duplicated faces (an export that wrote a layer twice) tie at every pixel they cover: more
    equal depths than the rasteriser notes per pass, so it renders again with room for all."""
    intr = Intrinsics(128, 96, 90.0, 90.0, 63.5, 47.5)
    gx, gy = np.meshgrid(np.linspace(-2.0, 2.0, 41), np.linspace(-1.5, 1.5, 31))
    pts = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 2.0) + 0.1 * gx.ravel()]
    w = gx.shape[1]
    k = np.arange(gx.size).reshape(gx.shape)[:-1, :-1].ravel()
    once = np.vstack([np.c_[k, k + 1, k + w + 1], np.c_[k, k + w + 1, k + w]])
    tris = np.vstack([once, once])
    raster = MeshRaster(pts, tris)
    n = intr.width * intr.height
    t, ids = np.empty(n, np.float32), np.empty(n, np.int32)
    raster.render(intr, np.eye(4), t, ids)
    assert raster.stats[3] > raster_mod.TIE_ROOM  # every covered pixel tied, beyond one pass's room
    ref = _cast(pts, tris, intr, np.eye(4))
    assert np.array_equal(ids, ref["ids"])
    assert np.array_equal(t, ref["t"])


def _pixel_sized_scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, Intrinsics, np.ndarray]:
    """Loose triangles of 0.3-4 pixels (facing the camera, seen edge-on, slivers, any) in front of
    a random pinhole, as far as 30 m from the survey frame's origin: the boxes the rasteriser
    decides with its per-triangle mask of pixel centres."""
    w, h = int(rng.integers(24, 80)), int(rng.integers(16, 60))
    f = float(rng.uniform(30, 300))
    intr = Intrinsics(w, h, f, f * float(rng.uniform(0.9, 1.1)), w / 2 + float(rng.normal(0, 3)),
                      h / 2 + float(rng.normal(0, 3)))
    n = int(rng.integers(200, 1500))
    dist = float(rng.uniform(0.3, 8.0))
    size = dist / f * float(rng.choice([0.3, 1.0, 2.0, 4.0]))
    centre = rng.normal(0, 1, (n, 3)) * [dist * w / f / 2, dist * h / f / 2, dist * 0.3] + [0.0, 0.0, dist]
    kind = rng.integers(0, 4, n)
    off = rng.normal(0, size, (n, 3, 3))
    off[kind == 1, 2] = off[kind == 1, 0] + rng.normal(0, size * 1e-4, (int(np.sum(kind == 1)), 3))
    off[kind == 2, :, 2] = 0.0
    off[kind == 3, :, 0] = 0.0
    shift = rng.normal(0, 30, 3) * (rng.random() < 0.5)
    vertices = (centre[:, None, :] + off).reshape(-1, 3) + shift
    target = shift + np.array([0.0, 0.0, dist]) + rng.normal(0, 0.2, 3)
    pose = look_at(shift + rng.normal(0, 0.05, 3), target, (0.0, -1.0, 0.0))
    return vertices, np.arange(3 * n).reshape(n, 3), intr, pose


def test_pixel_sized_triangles_equal_ray_casting_bit_for_bit() -> None:
    """Small boxes test only the pixel centres within the projected triangle pushed out by the
    rounding margin; none that ray casting hits may be left out, on any of these scenes."""
    rng = np.random.default_rng(11)
    hits = 0
    for _ in range(24):
        vertices, triangles, intr, pose = _pixel_sized_scene(rng)
        a = _agreement(vertices, triangles, intr, [pose])
        assert a["hit_agree"] == a["pixels"] and a["t_equal"] == a["both"], a
        assert a["same_triangle_or_normal"] == a["both"], a
        hits += a["hits"]
    assert hits > 5000
    # vertices on pixel rays 2-3 pixels apart: pixel centres on the projected edges, where ray
    # casting's one-ulp tolerance accepts centres a hair outside the exact triangle (without the
    # margin, 753 of the first grid's 3072 pixels were lost). Not bit for bit: a ray exactly
    # along the boundary of Embree's tree boxes may miss a triangle its own test would hit (here
    # 1 pixel of 3072 at the mesh's border, and up to 29 rays along shared edges that report the
    # neighbour; the same before the masks)
    intr = Intrinsics(64, 48, 50.0, 50.0, 31.0, 23.0)
    for step, tilt in ((2, 0.0), (2, 0.3), (3, -0.2)):
        u, v = np.meshgrid(np.arange(1, 63, step), np.arange(1, 47, step))
        z = 2.0 + tilt * (u - 31.0) / 50.0
        pts = np.c_[((u - 31.0) / 50.0 * z).ravel(), ((v - 23.0) / 50.0 * z).ravel(), z.ravel()]
        w = u.shape[1]
        k = np.arange(u.size).reshape(u.shape)[:-1, :-1].ravel()
        tris = np.vstack([np.c_[k, k + 1, k + w + 1], np.c_[k, k + w + 1, k + w]])
        a = _agreement(pts, tris, intr, [np.eye(4)])
        assert a["pixels"] - a["hit_agree"] <= 2, (step, tilt, a)
        assert a["max_dt"] <= 1e-6, (step, tilt, a)  # the other triangle at the shared edge: same depth
        assert a["both"] - a["same_triangle_or_normal"] <= 0.02 * a["both"], (step, tilt, a)


def test_lens_distortion_falls_back_to_ray_casting() -> None:
    room = Room()
    mesh = room.mesh(segments=64)
    distorted = Intrinsics(80, 60, 50.0, 50.0, 39.5, 29.5, "brown_conrady", (0.1, -0.05, 0.0, 0.0, 0.0))
    r = make_renderer("raster", mesh, distorted)
    assert isinstance(r, MeshCaster) and r.describe()["requested"] == "raster"
    assert isinstance(make_renderer("raster", mesh, INTR), MeshRasteriser)
    with pytest.raises(InputError):
        make_renderer("embree", mesh, INTR)


def test_study_grid_is_the_same_with_either_renderer() -> None:
    model = ErrorModel(a_per_m=0.002, b_m=0.004, sigma_per_m=0.0015)
    seq = make_sequence(frames=8, width=160, height=120, model=model, depth_units_m=1e-4, seed=3)
    traj = Trajectory(np.asarray(seq.timestamps_ns) * 1e-9, seq.poses)
    mesh = Room().mesh(subdivide_walls=3)
    grids = {}
    for name in ("raster", "raycast"):
        renderer = make_renderer(name, mesh, seq.info.depth_intrinsics, 1)
        res = evaluate_chunk(renderer, seq, traj, StudyConfig(renderer=name))
        grids[name] = res
    a, b = grids["raster"], grids["raycast"]
    assert a.grid.total > 100_000
    assert np.array_equal(a.stats, b.stats)
    assert np.array_equal(a.grid.count, b.grid.count)
    assert np.array_equal(a.grid.mean, b.grid.mean) and np.array_equal(a.grid.m2, b.grid.m2)


@pytest.mark.parametrize(("option", "message"), [
    (["--renderer", "embree"], "unknown renderer 'embree' (known: raster, raycast)"),
    (["--every", "0"], "Error: Invalid value for '--every': Input should be greater than or equal to 1"),
])
def test_bad_scan_options_are_one_line_input_errors_before_any_file_is_read(
        tmp_path: Any, capsys: pytest.CaptureFixture[str], option: list[str], message: str) -> None:
    from depthstation.app.cli import run_cli

    for name in ("seq.mcap", "poses.txt", "ref.ply"):
        (tmp_path / name).write_text("x")  # not an MCAP: the options must be refused first
    code = run_cli(["evaluate", "scan", "--sequence", str(tmp_path / "seq.mcap"), "--poses",
                    str(tmp_path / "poses.txt"), "--reference", str(tmp_path / "ref.ply"),
                    "--out", str(tmp_path / "out"), *option])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    # our own checks say one line; option types are click's (usage line, then the error)
    assert err[-1] == (message if message.startswith("Error:") else f"depthstation: error: {message}")



def test_without_a_normal_table_the_hits_are_the_same_and_no_table_is_held() -> None:
    """The study's renderer asks for no per-rank normal table (`render(table=False)`, its normals
    come from the float64 planes): the same depths and triangles as with the table, no table
    kept; and its planes, built straight in rank order, are the mesh-order planes reordered."""
    from depthstation.evaluate.scan.hit_refine import TrianglePlanes

    rng = np.random.default_rng(5)
    g = np.linspace(-1.5, 1.5, 121)
    gx, gy = np.meshgrid(g, g)
    pts = np.c_[gx.ravel(), gy.ravel(), rng.normal(0, 0.003, gx.size)]
    w = g.size
    k = np.arange(gx.size).reshape(gx.shape)[:-1, :-1].ravel()
    tris = np.vstack([np.c_[k, k + 1, k + w + 1], np.c_[k, k + w + 1, k + w]])
    pose = look_at(np.array([0.3, -0.2, 1.2]), np.array([0.2, 0.3, 0.0]), up=(0.3, 1.0, 0.0))
    n = INTR.width * INTR.height
    bare, full = MeshRaster(pts, tris), MeshRaster(pts, tris)
    t0, i0 = np.empty(n, np.float32), np.empty(n, np.int32)
    t1, i1 = np.empty(n, np.float32), np.empty(n, np.int32)
    bare.render(INTR, pose, t0, i0, ranks=True, table=False)
    full.render(INTR, pose, t1, i1, ranks=True)
    assert (i0 >= 0).sum() > n // 2
    assert np.array_equal(t0, t1) and np.array_equal(i0, i1)
    assert bare.normal_table().size == 0 and full.normal_table().shape == (len(tris), 3)
    ref = _cast(pts, tris, INTR, pose)
    hit = i1 >= 0
    assert np.array_equal(full.normal_table()[i1[hit]], ref["normals"][hit])
    ranked = TrianglePlanes(pts, tris, bare.perm)
    reordered = TrianglePlanes(pts, tris).reordered(bare.perm)
    for a in ("normal", "offset", "table"):
        assert np.array_equal(getattr(ranked, a), getattr(reordered, a)), a
