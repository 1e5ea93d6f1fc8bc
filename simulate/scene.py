"""Scenes to ray cast: a board on a rigid plate in front of a wall, a procedural room, or any mesh.

A scene is a list of surfaces, each a triangle mesh in world coordinates (metres) with an IR/visible
albedo and an RGB tint. Board scenes use the board frame as the world frame (x along the columns,
y down the rows, z into the board, origin at the outer top-left corner of the square grid).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from depthstation.core.board import Board
from depthstation.core.errors import InputError, SimulationError
from depthstation.core.mesh_checks import check_mesh, check_mesh_file

WHITE_ALBEDO = 0.85  # matte print paper
BLACK_ALBEDO = 0.05  # laser-printed black


@dataclass
class Surface:
    """One mesh (vertices Nx3 float, triangles Mx3 int) with its reflectance."""

    name: str
    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    albedo: float = 0.6
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    board_face: bool = False  # the plate's front face carries the board print


@dataclass
class Scene:
    """Surfaces plus the board (if any) whose print is on the `board_face` surface."""

    surfaces: list[Surface]
    board: Board | None = None
    texture: NDArray[np.float32] | None = None  # ChArUco albedo image over the square grid
    meta: dict[str, Any] = field(default_factory=dict)

    def raycasting_scene(self, nthreads: int = 0) -> Any:
        """An Open3D RaycastingScene holding every surface; geometry id = index in `surfaces`."""
        import open3d

        o3d: Any = open3d  # the stubs reject numpy arrays where the runtime takes them
        scene = o3d.t.geometry.RaycastingScene(nthreads=nthreads)
        for i, s in enumerate(self.surfaces):
            mesh = o3d.t.geometry.TriangleMesh()
            mesh.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(s.vertices, dtype=np.float32))
            mesh.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(s.triangles, dtype=np.int32))
            gid = scene.add_triangles(mesh)
            if gid != i:
                raise SimulationError(f"unexpected geometry id {gid} for surface {i}")
        return scene

    def board_albedo(self, x: NDArray[Any], y: NDArray[Any]) -> NDArray[np.float32]:
        """Albedo of the board print at board-frame points (plate white outside the grid)."""
        if self.board is None:
            raise SimulationError("scene has no board")
        if self.texture is None:
            black = self.board.is_black(x, y)
            return np.where(black, np.float32(BLACK_ALBEDO), np.float32(WHITE_ALBEDO)).astype(np.float32)
        tex = self.texture
        w, h = self.board.size_m
        ty, tx = tex.shape
        col = np.asarray(x) / w * tx - 0.5
        row = np.asarray(y) / h * ty - 0.5
        inside = self.board.inside(x, y)
        ci = np.clip(np.rint(col), 0, tx - 1).astype(np.int64)
        ri = np.clip(np.rint(row), 0, ty - 1).astype(np.int64)
        return np.where(inside, tex[ri, ci], np.float32(WHITE_ALBEDO)).astype(np.float32)

    def save_mesh(self, path: Path) -> Path:
        """All surfaces as one PLY/OBJ mesh (the reference scan of the scan study)."""
        import open3d

        o3d: Any = open3d

        verts, tris, off = [], [], 0
        for s in self.surfaces:
            verts.append(s.vertices)
            tris.append(s.triangles + off)
            off += len(s.vertices)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate(verts)),
                                         o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)))
        mesh.compute_vertex_normals()
        if not o3d.io.write_triangle_mesh(str(path), mesh):
            raise SimulationError(f"could not write mesh {path}")
        return path


def quad(corners: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Two triangles over 4 corners given in order around the quad."""
    return np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def box(lo: Any, hi: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Axis-aligned box from corner lo to corner hi (12 outward-facing triangles)."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)
    return v, t


def cylinder(center: Any, radius: float, y_top: float, y_bottom: float,
             segments: int = 64) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Closed vertical cylinder (y is down in our world frames) around `center` (x, z)."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    cx, cz = float(center[0]), float(center[1])
    ring = np.stack([cx + radius * np.cos(a), np.zeros(segments), cz + radius * np.sin(a)], axis=1)
    top = ring.copy()
    top[:, 1] = y_top
    bot = ring.copy()
    bot[:, 1] = y_bottom
    v = np.concatenate([top, bot, [[cx, y_top, cz], [cx, y_bottom, cz]]])
    tris = []
    for i in range(segments):
        j = (i + 1) % segments
        tris += [[i, j, segments + j], [i, segments + j, segments + i],
                 [2 * segments, j, i], [2 * segments + 1, segments + i, segments + j]]
    return v, np.asarray(tris, dtype=np.int64)


def _charuco_texture(board: Board, px_per_square: int = 64) -> NDArray[np.float32]:
    """Albedo image of a ChArUco board from OpenCV's own drawing (so detection ids match)."""

    name = str(board.dictionary or "DICT_4X4_50")
    if not hasattr(cv2.aruco, name):
        raise InputError(None, f"board.dictionary '{name}' is no OpenCV ArUco dictionary")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    cb = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_length_m,
                                float(board.marker_length_m or board.square_length_m * 0.75), dictionary)
    img = cb.generateImage((board.squares_x * px_per_square, board.squares_y * px_per_square),
                           marginSize=0, borderBits=1)
    # OpenCV draws the top-left square black; our Board says which colour it has
    # OpenCV's layout is fixed (top-left square black); the board definition must match the print
    grey = img.astype(np.float32) / 255.0
    return (BLACK_ALBEDO + (WHITE_ALBEDO - BLACK_ALBEDO) * grey).astype(np.float32)


def board_scene(board: Board | None = None, *, wall_gap_m: float = 0.30, plate_thickness_m: float = 0.012,
                floor_below_center_m: float = 1.25, wall_albedo: float = 0.55,
                floor_albedo: float = 0.35) -> Scene:
    """The checkerboard study's scene: the board printed on a rigid plate, a wall behind it, a floor."""
    board = board or Board()
    w, h = board.size_m
    m = board.plate_margin_m
    surfaces: list[Surface] = []
    v, t = quad(np.array([[-m, -m, 0.0], [w + m, -m, 0.0], [w + m, h + m, 0.0], [-m, h + m, 0.0]]))
    surfaces.append(Surface("board", v, t, WHITE_ALBEDO, board_face=True))
    v, t = box([-m, -m, 1e-4], [w + m, h + m, plate_thickness_m])
    surfaces.append(Surface("plate", v, t, 0.7, (0.9, 0.85, 0.75)))
    cx, cy = w / 2, h / 2
    floor_y = cy + floor_below_center_m
    zw = wall_gap_m
    v, t = quad(np.array([[cx - 30, floor_y - 30, zw], [cx + 30, floor_y - 30, zw],
                          [cx + 30, floor_y, zw], [cx - 30, floor_y, zw]]))
    surfaces.append(Surface("wall", v, t, wall_albedo, (1.0, 0.97, 0.9)))
    v, t = quad(np.array([[cx - 30, floor_y, zw], [cx + 30, floor_y, zw],
                          [cx + 30, floor_y, zw - 30], [cx - 30, floor_y, zw - 30]]))
    surfaces.append(Surface("floor", v, t, floor_albedo, (0.8, 0.75, 0.7)))
    texture = _charuco_texture(board) if board.type == "charuco" else None
    return Scene(surfaces, board, texture, {"kind": "board", "wall_gap_m": wall_gap_m,
                                            "floor_below_center_m": floor_below_center_m})


def room_scene(width_m: float = 6.0, depth_m: float = 8.0, height_m: float = 2.7,
               table_radius_m: float = 0.6, table_height_m: float = 0.75) -> Scene:
    """A procedural room for the reference-scan study; world: floor at y = 0, y up is -y (y down).

    The room spans x in [-W/2, W/2], z in [-D/2, D/2]; a round table stands at the origin, with a
    cabinet, a sofa-sized block, a shelf and two stools around it.
    """
    hw, hd = width_m / 2, depth_m / 2
    top = -height_m
    s: list[Surface] = []

    def add(name: str, vt: tuple[NDArray[np.float64], NDArray[np.int64]], albedo: float,
            tint: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
        s.append(Surface(name, vt[0], vt[1], albedo, tint))

    q = np.array
    warm, cool, wood = (1.0, 0.95, 0.85), (0.9, 0.95, 1.0), (0.7, 0.5, 0.3)
    add("floor", quad(q([[-hw, 0, -hd], [hw, 0, -hd], [hw, 0, hd], [-hw, 0, hd]])), 0.35, wood)
    add("ceiling", quad(q([[-hw, top, -hd], [hw, top, -hd], [hw, top, hd], [-hw, top, hd]])), 0.8)
    add("wall_n", quad(q([[-hw, 0, hd], [hw, 0, hd], [hw, top, hd], [-hw, top, hd]])), 0.6, warm)
    add("wall_s", quad(q([[-hw, 0, -hd], [hw, 0, -hd], [hw, top, -hd], [-hw, top, -hd]])), 0.6)
    add("wall_e", quad(q([[hw, 0, -hd], [hw, 0, hd], [hw, top, hd], [hw, top, -hd]])), 0.55, cool)
    add("wall_w", quad(q([[-hw, 0, -hd], [-hw, 0, hd], [-hw, top, hd], [-hw, top, -hd]])), 0.55)
    th = table_height_m
    add("table_top", cylinder([0, 0], table_radius_m, -th, -th + 0.04), 0.5, wood)
    add("table_leg", cylinder([0, 0], 0.06, -table_height_m + 0.04, 0.0, 24), 0.2)
    add("cabinet", box([hw - 0.5, -1.9, -1.5], [hw, 0, -0.3]), 0.65, (0.9, 0.9, 0.85))
    add("sofa", box([-hw, -0.8, -1.0], [-hw + 0.9, 0, 1.2]), 0.3, (0.4, 0.45, 0.6))
    add("shelf", box([-1.0, -1.6, hd - 0.35], [0.6, 0, hd]), 0.45, (0.8, 0.6, 0.4))
    add("stool_1", cylinder([1.1, 0.5], 0.2, -0.45, 0.0, 24), 0.25)
    add("stool_2", cylinder([-0.9, -0.9], 0.2, -0.45, 0.0, 24), 0.25)
    add("box", box([-0.15, -th - 0.25, -0.15], [0.15, -th, 0.1]), 0.75, (1.0, 0.8, 0.6))
    return Scene(s, None, None, {"kind": "room", "width_m": width_m, "depth_m": depth_m,
                                 "height_m": height_m, "table_radius_m": table_radius_m,
                                 "table_height_m": table_height_m})


def mesh_scene(path: Path, albedo: float = 0.6) -> Scene:
    """Any PLY/OBJ triangle mesh as one surface (metres, in its own frame)."""
    import open3d

    o3d: Any = open3d

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "scene mesh not found")
    check_mesh_file(p)
    mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) == 0:
        raise InputError(p, "not a triangle mesh (no triangles read; PLY or OBJ expected)")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    t = np.asarray(mesh.triangles, dtype=np.int64)
    check_mesh(p, v, t)
    return Scene([Surface(p.stem, v, t, albedo)], None, None, {"kind": "mesh", "path": str(p)})


def load_scene(name_or_path: str | Path, board: Board | None = None) -> Scene:
    """'board', 'room' or the path of a PLY/OBJ mesh."""
    s = str(name_or_path)
    if s == "room":
        return room_scene()
    if s == "board":
        return board_scene(board)
    return mesh_scene(Path(s))
