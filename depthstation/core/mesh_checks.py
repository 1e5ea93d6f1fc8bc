"""What every triangle mesh read from a user's file must satisfy before rays meet it (the scan
study's reference, the simulator's scene), each a one-line InputError naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import InputError


def check_mesh_file(path: Path) -> None:
    """A PLY that is empty or lacks its magic is refused before Open3D reads it (its reader prints
    its own C++ line, 'RPly: Unable to read magic number', beside our one-line error)."""
    p = Path(path)
    if p.suffix.lower() != ".ply":
        return
    with p.open("rb") as f:
        head = f.read(4)
    if not head.startswith(b"ply"):
        raise InputError(p, "is no PLY file (empty, or it does not begin with 'ply')")


def check_mesh(path: Path, vertices: NDArray[np.floating], triangles: NDArray[np.integer]) -> None:
    """Triangle indices within the vertex list, and finite vertices: a NaN vertex makes its
    triangles holes the rays pass through (to the floor behind a table top), so the grid, or the
    rendered depth, would move without a word."""
    v = np.asarray(vertices)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        outside = (t < 0) | (t >= len(v))
        k = int(np.flatnonzero(outside.any(axis=1))[0])
        index = int(t[k][outside[k]][0])
        raise InputError(path, f"triangle {k} names vertex {index}, which the {len(v)} vertices do not "
                               "hold: the file is broken")
    bad = np.asarray(~np.isfinite(v).all(axis=1), dtype=bool)
    if not bad.any():
        return
    used = np.zeros(len(v), bool)
    used[t.ravel()] = True
    holes = int(np.count_nonzero(bad[t].any(axis=1)))
    first = int(np.flatnonzero(bad)[0])
    raise InputError(path, f"{int(bad.sum())} of {len(v)} vertices are not finite numbers (NaN or "
                           f"inf; the first is vertex {first}), {holes} triangles use them: the rays would "
                           "pass through those holes; repair the mesh or remove them"
                           + ("" if used[bad].any() else " (they are unused: remove them)"))
