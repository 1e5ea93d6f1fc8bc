"""The TUM trajectory format (`timestamp tx ty tz qx qy qz qw`, camera-to-world): one reader for the
scan study, explain and the simulator, so a file one command takes the others take too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import InputError
from depthstation.core.geometry import quaternion_to_matrix
from depthstation.core.text_files import read_text


def read_tum_poses(path: Path, wxyz: bool = False) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Time stamps (s, increasing) and camera-to-world 4x4 poses of a TUM trajectory. Comment (#)
    and blank lines are skipped; lines are taken in time order; the same line twice is kept once,
    two different poses at one time are refused; non-finite values and zero quaternions are
    refused naming their line. `wxyz`: the file's quaternion columns are qw qx qy qz (Eigen's
    coefficient order and several trackers'), not TUM's qx qy qz qw."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trajectory file not found")
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(read_text(path, "TUM trajectory").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(path, f"line {lineno}: expected 8 values "
                                   f"(timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            row = [float(p) for p in parts]
        except ValueError as exc:
            raise InputError(path, f"line {lineno}: not a number ({exc})") from exc
        if not all(np.isfinite(row)):  # a NaN pose is a tracking loss to leave out, not a pose
            names = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
            bad = ", ".join(n for n, v in zip(names, row, strict=True) if not np.isfinite(v))
            raise InputError(path, f"line {lineno}: {bad} not finite (leave the frames a tracker lost "
                                   "out of the file)")
        if np.linalg.norm(row[4:8]) < 1e-9:
            raise InputError(path, f"line {lineno}: zero quaternion (qx qy qz qw all 0)")
        rows.append(row)
        lines.append(lineno)
    if not rows:
        raise InputError(path, "trajectory has no poses")
    a = np.asarray(rows)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    at = np.asarray(lines)[order]
    same_t = np.flatnonzero(np.diff(a[:, 0]) == 0)
    if same_t.size:  # two files joined, or one written twice: the same line twice is harmless
        clash = [k for k in same_t if not np.array_equal(a[k], a[k + 1])]
        if clash:
            k = clash[0]
            more = f" ({len(clash)} such times)" if len(clash) > 1 else ""
            raise InputError(path, f"lines {at[k]} and {at[k + 1]} give two different poses at "
                                   f"t={float(a[k, 0]):.9f}{more}")
        keep = np.ones(len(a), bool)
        keep[same_t + 1] = False
        a = a[keep]
    poses = np.tile(np.eye(4), (a.shape[0], 1, 1))
    for i, row in enumerate(a):
        q = row[[5, 6, 7, 4]] if wxyz else row[4:8]
        poses[i, :3, :3] = quaternion_to_matrix(q / np.linalg.norm(q))
        poses[i, :3, 3] = row[1:4]
    return a[:, 0], poses
