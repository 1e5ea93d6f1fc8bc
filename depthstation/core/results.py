"""Self-describing result folders: every evaluation writes `result.json` next to its tables, and any
later command reads a folder back by its files (see docs/results.md).

A result folder is recognised by its files, not only by `result.json`'s kind, so folders written by
any version of a stage (or by hand, in the documented formats) can be compared.
"""

from __future__ import annotations

import csv
import json
import platform
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import InputError
from depthstation.core.grid import GRID_FILE

RESULT_FILE = "result.json"
# the files a result folder is recognised by (docs/results.md)
STANDPOINTS_FILE = "standpoints.csv"
FRAMES_FILE = "frames.csv"
SUMMARY_FILE = "summary.json"
EXPLAIN_FILE = "explain.json"
_PACKAGES = ("depthstation", "numpy", "opencv-python-headless", "open3d", "pyrealsense2",
             "rerun-sdk", "mcap", "rosbags", "scipy", "numba")


def software_versions() -> dict[str, str]:
    """Versions of Python and the packages that shape the numbers."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_json(path: Path, data: Any) -> None:
    """JSON with numpy values turned into plain ones and NaN/inf into null; written atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    tmp.replace(path)


def write_result_info(out_dir: Path, kind: str, inputs: list[str], parameters: dict[str, Any],
                      device: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> Path:
    """`result.json`: what this folder holds, made from what, by which software, when."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    info = {
        "kind": kind,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "inputs": [str(i) for i in inputs],
        "parameters": parameters,
        "device": device or {},
        "software": software_versions(),
    }
    if extra:
        info.update(extra)
    path = out_dir / RESULT_FILE
    write_json(path, info)
    return path


def read_result_info(out_dir: Path) -> dict[str, Any]:

    path = Path(out_dir) / RESULT_FILE
    if not path.is_file():
        raise InputError(out_dir, f"not a result folder (no {RESULT_FILE})")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"broken JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(path, "broken result.json (expected an object)")
    return data


@dataclass
class ResultFolder:
    path: Path
    kind: str                       # 'checkerboard' | 'scan' | 'explain'
    info: dict[str, Any] = field(default_factory=dict)   # result.json ({} if the folder has none)

    @property
    def label(self) -> str:
        return self.path.name


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
