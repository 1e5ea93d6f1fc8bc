"""Self-describing result folders: every evaluation writes `result.json` next to its tables."""

from __future__ import annotations

import json
import platform
import sys
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

RESULT_FILE = "result.json"
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
    from depthstation.errors import InputError

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
