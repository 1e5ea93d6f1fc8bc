"""The measured field an error model is fitted to: a scan study's grid (coarsened to table cells)
or a checkerboard study's standpoints, as rows of (distance, inclination, count, mean, std, their
standard errors), with the camera the result names.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import stdtrit

from depthstation.core.capture.registry import open_recording
from depthstation.core.errors import DepthstationError, InputError
from depthstation.core.grid import GRID_FILE, Grid
from depthstation.core.results import (
    RESULT_FILE,
    STANDPOINTS_FILE,
    SUMMARY_FILE,
    fingerprint,
    read_result_info,
)

F64 = NDArray[np.float64]
# the camera keys a model is bound to and `correct` checks (identity), and those it reports (mode)
IDENTITY_KEYS = ("model", "serial_number", "resolution")
MODE_KEYS = ("firmware_version", "preset", "depth_units_m", "baseline_m")


@dataclass
class Field:
    """Rows of the measured field of one input (one row per table cell or standpoint)."""

    path: Path
    kind: str                      # 'scan' | 'checkerboard'
    z_m: F64                       # cell centre / standpoint distance
    theta_deg: F64
    z_lo: F64
    z_hi: F64
    theta_lo: F64
    theta_hi: F64
    count: NDArray[np.int64]
    mean_m: F64
    std_m: F64
    se_mean_m: F64                 # standard error of mean_m (frames as clusters, conservative)
    se_std_m: F64                  # standard error of std_m
    u95_m: F64
    cluster: NDArray[np.int64]     # cells that share frames: one cluster (block of cells, standpoint)
    labels: list[str]
    camera: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    domain: F64 | None = None      # K x 4 boxes where the input measured; None: its rows' own boxes

    def domain_boxes(self) -> F64:
        if self.domain is not None:
            return self.domain
        return np.stack([self.z_lo, self.z_hi, self.theta_lo, self.theta_hi], axis=-1)

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for i in range(len(self.z_m)):
            out.append({"source": self.labels[i], "distance_m": float(self.z_m[i]),
                        "distance_lo_m": float(self.z_lo[i]), "distance_hi_m": float(self.z_hi[i]),
                        "inclination_deg": float(self.theta_deg[i]),
                        "inclination_lo_deg": float(self.theta_lo[i]),
                        "inclination_hi_deg": float(self.theta_hi[i]), "count": int(self.count[i]),
                        "mean_m": float(self.mean_m[i]), "std_m": float(self.std_m[i]),
                        "u95_m": float(self.u95_m[i]), "se_m": float(self.se_mean_m[i])})
        return out


def device_model(name: Any) -> str | None:
    """The camera model a device name ends with ('Intel RealSense D455' -> 'D455'; the product id
    in brackets dropped), so that a D435I is not a D435."""
    if not name:
        return None
    words = str(name).split("(")[0].split()
    return words[-1].upper() if words else None


def _camera(device: dict[str, Any], resolution: list[int] | None, calibration: Any,
            intrinsics: dict[str, Any] | None) -> dict[str, Any]:
    return {"name": device.get("name"), "model": device_model(device.get("name")),
            "serial_number": device.get("serial_number"),
            "firmware_version": device.get("firmware_version") or device.get("firmware"),
            "preset": device.get("preset") or device.get("visual_preset"),
            "depth_units_m": device.get("depth_units_m"), "baseline_m": device.get("baseline_m"),
            "resolution": resolution, "depth_intrinsics": intrinsics, "calibration": calibration}


def _source_camera(path: Path | None, device: dict[str, Any]) -> dict[str, Any]:
    """The camera of a result from the recording it was made from, where it is still on disk
    (resolution, calibration, firmware); else what result.json says alone."""
    if path is not None and path.exists():
        try:
            rec = open_recording(path)
        except DepthstationError:
            rec = None
        if rec is not None:
            dev = {**device, **dict(rec.metadata.get("device") or rec.info.device or {})}
            dev.setdefault("depth_units_m", rec.info.depth_units_m)
            if rec.info.baseline_m is not None:
                dev.setdefault("baseline_m", rec.info.baseline_m)
            i = rec.info.depth_intrinsics
            return _camera(dev, [int(i.width), int(i.height)],
                           rec.metadata.get("calibration"), i.to_dict())
    return _camera(device, None, None, None)


def _divisor_near(n: int, want: int) -> int:
    """The divisor of n nearest to `want` (coarsening needs whole blocks)."""
    divs = [d for d in range(1, n + 1) if n % d == 0]
    return min(divs, key=lambda d: (abs(d - want), -d))


def read_scan(path: Path, distance_bin_m: float, inclination_bin_deg: float, min_count: int,
              info: dict[str, Any]) -> Field:
    """A scan study's grid as table cells of about `distance_bin_m` x `inclination_bin_deg`.

    A table cell's mean is the exact merge of its analysis cells; its standard error is bounded
    from above by sum_c (n_c / N) se_c (the analysis cells' frame-clustered errors taken as fully
    correlated: they share their frames), since the frame moments do not coarsen exactly."""
    grid = Grid.load(path / GRID_FILE)
    nd, ni = grid.shape
    d_step = float(grid.distance_edges_m[1] - grid.distance_edges_m[0])
    i_step = float(grid.inclination_edges_deg[1] - grid.inclination_edges_deg[0])
    fd = _divisor_near(nd, max(1, round(distance_bin_m / d_step)))
    fi = _divisor_near(ni, max(1, round(inclination_bin_deg / i_step)))
    coarse = grid.coarsened(fd, fi)
    se_fine = grid.se_m
    feff = grid.effective_frames
    cnt = grid.count.astype(np.float64)
    se_fill = np.where(np.isfinite(se_fine), se_fine, 0.0)
    blocks = (nd // fd, fd, ni // fi, fi)
    n_blk = cnt.reshape(blocks).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        se_blk = (cnt * se_fill).reshape(blocks).sum(axis=(1, 3)) / n_blk
        indep = np.sqrt(coarse.var / coarse.count)
        se_blk = np.fmax(se_blk, indep)   # never below the independent-sample figure
        if feff is not None:
            fe = np.where(np.isfinite(feff), feff, 1.0)
            fe_blk = (cnt * fe).reshape(blocks).sum(axis=(1, 3)) / n_blk
        else:
            fe_blk = coarse.count.astype(np.float64)
        deff = np.fmax(coarse.count * se_blk ** 2 / coarse.var, 1.0)
    ok = (coarse.count >= max(min_count, 3)) & np.isfinite(se_blk) & (se_blk > 0) & np.isfinite(coarse.var)
    ids = np.argwhere(ok)
    de, ie = coarse.distance_edges_m, coarse.inclination_edges_deg
    k, j = ids[:, 0], ids[:, 1]
    n = coarse.count[k, j]
    std = np.sqrt(coarse.var[k, j])
    n_eff = np.maximum(n / deff[k, j], 2.0)
    dof = np.maximum(fe_blk[k, j] - 1.0, 1.0)
    se = se_blk[k, j]
    # cells that share frames: blocks of about 0.5 m x 15 deg (their errors are correlated through
    # the frames' poses; the coefficients' covariance is clustered on them)
    cd = max(1, round(0.5 / (de[1] - de[0])))
    ci = max(1, round(15.0 / (ie[1] - ie[0])))
    cluster = (k // cd) * 10_000 + (j // ci)
    summ: dict[str, Any] = {}
    sp = path / SUMMARY_FILE
    if sp.is_file():
        try:
            summ = json.loads(sp.read_text())
        except (OSError, json.JSONDecodeError):
            summ = {}
    seq = (summ.get("inputs") or {}).get("sequence")
    cam = _source_camera(Path(seq) if seq else None, dict(info.get("device") or {}))
    if cam["resolution"] is None and isinstance((summ.get("sequence") or {}).get("intrinsics"), dict):
        intr = summ["sequence"]["intrinsics"]
        cam["resolution"] = [int(intr["width"]), int(intr["height"])]
        cam["depth_intrinsics"] = intr
    if cam["depth_units_m"] is None:
        cam["depth_units_m"] = (summ.get("sequence") or {}).get("depth_units_m")
    notes = [f"table cells of {de[1] - de[0]:.3g} m x {ie[1] - ie[0]:.3g} deg ({fd} x {fi} analysis bins); "
             f"cells with at least {max(min_count, 3)} samples"]
    if grid.moments is None:
        notes.append("the grid has no frame moments: its standard errors treat pixels as independent "
                     "(an underestimate)")
    return Field(path, "scan", 0.5 * (de[k] + de[k + 1]), 0.5 * (ie[j] + ie[j + 1]), de[k], de[k + 1],
                 ie[j], ie[j + 1], n.astype(np.int64), coarse.mean[k, j], std, se,
                 std / np.sqrt(2.0 * (n_eff - 1.0)), np.asarray(stdtrit(dof, 0.975) * se, dtype=np.float64),
                 cluster.astype(np.int64), [path.name] * len(k), cam, notes)


def _number(row: dict[str, str], key: str, path: Path, name: str) -> float:
    text = row.get(key)
    if text is None:
        raise InputError(path, f"has no column '{key}'")
    try:
        return float(text) if text != "" else math.nan
    except ValueError as exc:
        raise InputError(path, f"standpoint {name}: '{key}' is no number ({text!r})") from exc


def read_checkerboard(path: Path, info: dict[str, Any]) -> Field:
    """A checkerboard study's standpoints: accuracy (mean signed error) and noise (the RMS to the
    frame's plane) at the board centre's distance and inclination, each its own cluster. The
    standard errors are the table's U95 over t(0.975, frames - 1)."""
    table = path / STANDPOINTS_FILE
    with table.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    z, t, cnt, mean, std, u95, se, sse, labels = [], [], [], [], [], [], [], [], []
    for r in rows:
        name = r.get("standpoint", "?")
        keys = ("distance_m", "inclination_deg", "frames", "accuracy_m", "accuracy_m_u95", "noise_m",
                "noise_m_u95")
        vals = {k: _number(r, k, table, name) for k in keys}
        if not all(math.isfinite(v) for v in vals.values()) or vals["frames"] < 2:
            continue
        k95 = float(stdtrit(max(vals["frames"] - 1.0, 1.0), 0.975))
        z.append(vals["distance_m"])
        t.append(vals["inclination_deg"])
        cnt.append(int(vals["frames"]))
        mean.append(vals["accuracy_m"])
        std.append(vals["noise_m"])
        u95.append(vals["accuracy_m_u95"])
        se.append(vals["accuracy_m_u95"] / k95)
        sse.append(vals["noise_m_u95"] / k95)
        labels.append(f"{path.name}/{name}")
    za, ta = np.asarray(z, dtype=np.float64), np.asarray(t, dtype=np.float64)
    # the table's errors are orthogonal to the board; along the ray they are 1 / cos(theta) longer,
    # and the model's bias is a z-depth error (the board centre's angle off the axis neglected:
    # under 3 % within 14 deg of the optical axis)
    along = 1.0 / np.cos(np.radians(ta))
    # a standpoint's board spans distances and inclinations around its centre's (its row's box: 5 %,
    # 5 deg); the domain is the span of the standpoints, so widened (a model fitted to standpoints
    # is a smooth surface between them, which held-out standpoints test)
    summ_path = path / SUMMARY_FILE
    first = None
    if summ_path.is_file():
        try:
            stands = json.loads(summ_path.read_text()).get("standpoints") or []
            first = Path(stands[0]["path"]) if stands and stands[0].get("path") else None
        except (OSError, json.JSONDecodeError, KeyError, TypeError):
            first = None
    cam = _source_camera(first, dict(info.get("device") or {}))
    span = (np.asarray([[za.min() * 0.95, za.max() * 1.05, max(ta.min() - 5.0, 0.0),
                         min(ta.max() + 5.0, 90.0)]]) if len(za) else None)
    return Field(path, "checkerboard", za, ta, za * 0.95, za * 1.05, np.maximum(ta - 5.0, 0.0),
                 np.minimum(ta + 5.0, 90.0), np.asarray(cnt, dtype=np.int64), np.asarray(mean) * along,
                 np.asarray(std) * along, np.asarray(se) * along, np.asarray(sse) * along,
                 np.asarray(u95) * along,
                 np.arange(len(za), dtype=np.int64), labels, cam,
                 ["standpoints: accuracy_m as the bias, noise_m as sigma, both orthogonal to the board and "
                  "taken along the ray (/ cos inclination) as z-depth errors; U95 / t(0.975, frames - 1) as "
                  "their standard errors"], span)


def read_result(path: Path, distance_bin_m: float, inclination_bin_deg: float, min_count: int) -> Field:
    """One result folder: a scan study (grid.npz) or a checkerboard study (standpoints.csv)."""
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "is no result folder (give the folder a scan or checkerboard study wrote)")
    info = read_result_info(path) if (path / RESULT_FILE).is_file() else {}
    if (path / GRID_FILE).is_file():
        f = read_scan(path, distance_bin_m, inclination_bin_deg, min_count, info)
    elif (path / STANDPOINTS_FILE).is_file():
        f = read_checkerboard(path, info)
    else:
        raise InputError(path, f"is no scan or checkerboard result (no {GRID_FILE}, no {STANDPOINTS_FILE})")
    if len(f.z_m) == 0:
        raise InputError(path, "holds no cell or standpoint to fit (too few samples per cell: lower "
                               "--min-count, or the study measured nothing)")
    return f


def input_record(f: Field) -> dict[str, Any]:
    """What the model file says of one input: path, kind, rows used, fingerprint of its data file."""
    data = f.path / (GRID_FILE if f.kind == "scan" else STANDPOINTS_FILE)
    return {"path": str(f.path), "kind": f.kind, "rows": len(f.z_m), "notes": f.notes,
            "fingerprint": fingerprint(data)}


def one_camera(fields: list[Field]) -> dict[str, Any]:
    """The camera all inputs share; inputs of two cameras (model, serial, resolution) are refused."""
    cam = dict(fields[0].camera)
    for f in fields[1:]:
        for key in IDENTITY_KEYS:
            a, b = cam.get(key), f.camera.get(key)
            if a is not None and b is not None and a != b:
                raise InputError(f.path, f"is of another camera than {fields[0].path} ({key} {b!r} vs "
                                         f"{a!r}): a model describes one camera; fit each separately")
            if a is None and b is not None:
                cam[key] = b
        for key in (*MODE_KEYS, "name", "depth_intrinsics", "calibration"):
            if cam.get(key) is None and f.camera.get(key) is not None:
                cam[key] = f.camera[key]
    return cam
