"""Reading result folders back: what kind each is (checkerboard, scan, explain) and its tables/grids.

A result folder is recognised by its files, not only by `result.json`'s kind, so folders written by
any version of a stage (or by hand, in the documented formats) can be compared. See docs/results.md.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.errors import InputError
from depthstation.results import RESULT_FILE

STANDPOINTS_FILE = "standpoints.csv"
GRID_FILE = "grid.npz"
EXPLAIN_FILE = "explain.json"
GRID_KEYS = ("distance_edges_m", "inclination_edges_deg", "count", "mean_m", "var_m2")


@dataclass
class GridData:
    """The contents of a `grid.npz` (arrays shaped distance x inclination)."""

    distance_edges_m: NDArray[np.float64]
    inclination_edges_deg: NDArray[np.float64]
    count: NDArray[np.int64]
    mean_m: NDArray[np.float64]
    var_m2: NDArray[np.float64]

    @property
    def std_m(self) -> NDArray[np.float64]:
        return np.sqrt(np.where(self.var_m2 >= 0, self.var_m2, np.nan))


@dataclass
class ResultFolder:
    path: Path
    kind: str                       # 'checkerboard' | 'scan' | 'explain'
    info: dict[str, Any] = field(default_factory=dict)   # result.json ({} if the folder has none)

    @property
    def label(self) -> str:
        return self.path.name


def read_grid(path: Path) -> GridData:
    """Load a `grid.npz`; a missing key is an input error naming the key."""
    try:
        with np.load(path) as z:
            missing = [k for k in GRID_KEYS if k not in z.files]
            if missing:
                raise InputError(path, f"grid file lacks {', '.join(missing)}")
            data = {k: np.asarray(z[k]) for k in GRID_KEYS}
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read grid ({exc})") from exc
    grid = GridData(data["distance_edges_m"].astype(np.float64),
                    data["inclination_edges_deg"].astype(np.float64),
                    data["count"].astype(np.int64), data["mean_m"].astype(np.float64),
                    data["var_m2"].astype(np.float64))
    shape = (grid.distance_edges_m.size - 1, grid.inclination_edges_deg.size - 1)
    for name in ("count", "mean_m", "var_m2"):
        if getattr(grid, name).shape != shape:
            raise InputError(path, f"{name} has shape {getattr(grid, name).shape}, edges imply {shape}")
    return grid


def _number(text: str) -> Any:
    if text == "":
        return float("nan")
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def read_standpoints(path: Path) -> list[dict[str, Any]]:
    """Rows of a `standpoints.csv`, numbers parsed (empty cells become NaN)."""
    try:
        with Path(path).open(newline="") as fh:
            rows = [{k: (_number(v) if k != "standpoint" else v) for k, v in row.items()}
                    for row in csv.DictReader(fh)]
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc})") from exc
    if rows and not {"standpoint", "distance_m", "inclination_deg"} <= set(rows[0]):
        raise InputError(path, "needs the columns standpoint, distance_m, inclination_deg")
    return rows


def open_result(path: Path) -> ResultFolder:
    """Recognise a result folder by its files; result.json is read when present."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "not a folder")
    info: dict[str, Any] = {}
    if (path / RESULT_FILE).is_file():
        try:
            loaded = json.loads((path / RESULT_FILE).read_text())
        except json.JSONDecodeError as exc:
            raise InputError(path / RESULT_FILE, f"broken JSON ({exc})") from exc
        info = loaded if isinstance(loaded, dict) else {}
    if (path / STANDPOINTS_FILE).is_file():
        kind = "checkerboard"
    elif (path / GRID_FILE).is_file():
        kind = "scan"
    elif (path / EXPLAIN_FILE).is_file():
        kind = "explain"
    else:
        raise InputError(path, f"not a result folder (no {STANDPOINTS_FILE}, {GRID_FILE} or {EXPLAIN_FILE})")
    return ResultFolder(path=path, kind=kind, info=info)


def unique_labels(folders: list[ResultFolder]) -> list[str]:
    """Short labels for tables: folder names, made unique with their parent's name when they clash."""
    labels = [f.label for f in folders]
    for i, lab in enumerate(labels):
        if labels.count(lab) > 1:
            labels[i] = f"{folders[i].path.parent.name}/{lab}"
    seen: dict[str, int] = {}
    out = []
    for lab in labels:
        seen[lab] = seen.get(lab, 0) + 1
        out.append(lab if seen[lab] == 1 else f"{lab}#{seen[lab]}")
    return out
