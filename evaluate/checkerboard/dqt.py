"""Intel's Depth Quality Tool (librealsense `tools/depth-quality`) metrics, beside the paper's.

Why: D455 owners compare against the DQT and Intel's datasheet; these are the DQT's own
definitions (depth-metrics.h, rs-depth-quality.cpp), computed per frame on the board mask (and on
a centred ROI like the DQT's `--roi 40` when asked), averaged over the standpoint's frames:

- fill rate [%]: valid (non-zero) pixels / ROI pixels;
- plane fit: dominant-axis least squares on *all* valid points (ilikebigbits, not SVD); the
  metrics then drop 0.5 % of the points at each end *of z* (not of the residual);
- plane-fit RMS [mm] of the orthogonal distances, and [% of distance], distance = the plane's
  perpendicular distance from the camera (-d);
- subpixel RMS [px]: RMS of f B / Z - f B / Z_plane, Z the pixel's z-depth and Z_plane the
  plane's along the same ray: the DQT's help text ("Di = BL*FL/Zi; Dpi = BL*FL/Zpi"), which is
  the disparity residual itself. The tool's code takes ranges |p| and the orthogonal projection
  instead, which reads low off the image centre (x cos^3 of the off-axis angle: -10 % over the
  DQT's 40 % ROI of a D455); that value is reported too (`subpixel_rms_tool_px`);
- Z accuracy [% of ground truth]: the *upper median* of (pivot z - GT + distance to the plane),
  pivot = the fitted plane where the pivot ray meets it; positive = the plane fit is farther than
  the ground truth (the DQT's sign). Our ground truth is the reference plane from the board pose
  along the same ray (the DQT asks the user for one number);
- temporal noise [%]: per pixel std / median over up to 39 frames (zeros left out, empty pixels
  count as 0), the median over the ROI's pixels.

Intel's expected RMS (tuning white paper): RMS_z = Z^2 * subpixel / (f * B), f the stereo
imager's focal length (px), B the baseline; reported with subpixel = 0.08 px (Intel's advice for a
well calibrated D4xx) and the ratio measured / expected. Where our definitions and the DQT's
differ, and why: docs/checkerboard-study.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from depthstation.evaluate.checkerboard.kernels import board_moments

F64 = NDArray[np.float64]
EXPECTED_SUBPIXEL_PX = 0.08  # Intel: "best to use about 0.08" for a well calibrated D4xx
TEMPORAL_FRAMES = 39         # the DQT's 40-frame FIFO pops the oldest before computing
TRIM_DIVISOR = 200           # 0.5 % of the points at each end of z

# standpoints.csv columns (mean over frames unless said), board mask first, then the centred ROI
METRICS = ("fill_rate_pct", "distance_mm", "plane_fit_rms_mm", "plane_fit_rms_pct", "subpixel_rms_px",
           "subpixel_rms_tool_px", "z_accuracy_pct", "temporal_noise_pct", "expected_rms_mm", "rms_ratio")
DQT_COLUMNS = tuple(f"dqt_{m}" for m in METRICS) + tuple(f"dqt_roi_{m}" for m in METRICS)


@dataclass
class DqtFrame:
    """The DQT's figures of one frame and one ROI (plus what Z accuracy needs once the reference
    plane is known)."""

    fill_rate_pct: float
    distance_mm: float = float("nan")
    plane_fit_rms_mm: float = float("nan")
    plane_fit_rms_pct: float = float("nan")
    subpixel_rms_px: float = float("nan")
    subpixel_rms_tool_px: float = float("nan")
    pivot_ray: tuple[float, float, float] = (0.0, 0.0, 1.0)  # camera ray (z = 1) of the pivot
    pivot_z_mm: float = float("nan")                       # fitted plane's z along the pivot ray
    median_distance_mm: float = float("nan")               # upper median of the trimmed residuals

    def z_accuracy_pct(self, ground_truth_mm: float) -> float:
        """DQT Z accuracy against a ground-truth z-depth (mm) along the pivot ray."""
        if not np.isfinite(ground_truth_mm) or ground_truth_mm <= 0:
            return float("nan")
        return float(100.0 * (self.pivot_z_mm - ground_truth_mm + self.median_distance_mm) / ground_truth_mm)


def centred_roi(width: int, height: int, fraction: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the DQT's centred ROI: `fraction` of each side (0.4: 16 % of the area)."""
    return (int(width * (0.5 - 0.5 * fraction)), int(height * (0.5 - 0.5 * fraction)),
            int(width * (0.5 + 0.5 * fraction)), int(height * (0.5 + 0.5 * fraction)))


def plane_from_sums(n: float, s: F64, ss: F64) -> tuple[F64, float] | None:
    """The DQT's plane fit (ilikebigbits' 'plane from points') from the point count, the sums of
    x, y, z and of their products (xx, xy, xz, yy, yz, zz): the largest of the three 2x2
    determinants picks the axis the regression solves for. Returns (unit normal away from the
    camera, d) with n.p + d = 0, or None for fewer than 3 points or a degenerate set."""
    if n < 3:
        return None
    c = s / n
    xx = ss[0] - n * c[0] * c[0]
    xy = ss[1] - n * c[0] * c[1]
    xz = ss[2] - n * c[0] * c[2]
    yy = ss[3] - n * c[1] * c[1]
    yz = ss[4] - n * c[1] * c[2]
    zz = ss[5] - n * c[2] * c[2]
    det_x, det_y, det_z = yy * zz - yz * yz, xx * zz - xz * xz, xx * yy - xy * xy
    det_max = max(det_x, det_y, det_z)
    if det_max <= 0:
        return None
    if det_max == det_x:
        v = np.array([det_x, xz * yz - xy * zz, xy * yz - xz * yy])
    elif det_max == det_y:
        v = np.array([xz * yz - xy * zz, det_y, xy * xz - yz * xx])
    else:
        v = np.array([xy * yz - xz * yy, xy * xz - yz * xx, det_z])
    v /= np.linalg.norm(v)
    if v @ c < 0:
        v = -v
    return v, float(-(v @ c))


@njit(cache=True, nogil=True)
def _histogram(raw: Any, inside: Any, hist: Any) -> None:  # pragma: no cover - compiled
    """Counts of each raw depth value over the ROI (for the trimming by z without a sort)."""
    h, w = raw.shape
    for i in range(h):
        for j in range(w):
            if inside[i, j]:
                hist[raw[i, j]] += 1


def _trim_bounds(hist: NDArray[np.int64], n: int, k: int) -> tuple[int, int, int, int]:
    """(lo, drop_lo, hi, drop_hi): values below lo and above hi leave, and that many of the values
    equal to lo / hi, so that exactly k leave at each end (0 = no depth is not counted)."""
    hist[0] = 0
    c = np.cumsum(hist)
    lo = int(np.searchsorted(c, k))                 # the k-th smallest value
    hi = int(np.searchsorted(c, n - k + 1))         # the k-th largest value
    below, above = (int(c[lo - 1]) if lo > 0 else 0), n - int(c[hi])
    return lo, k - below, hi, k - above


@njit(cache=True, nogil=True)
def _residuals(raw: Any, inside: Any, ray_x: Any, ray_y: Any, units: float, nx: float, ny: float,
               nz: float, d0: float, lo: int, drop_lo: int, hi: int, drop_hi: int, bf: float,
               dist: Any, acc: Any) -> int:  # pragma: no cover - compiled
    """Orthogonal distances of the trimmed points (into `dist`) and the sums of squares of the
    distances, the disparity residuals along the rays and the tool's range-based ones."""
    h, w = raw.shape
    k = 0
    for i in range(h):
        for j in range(w):
            d = raw[i, j]
            if d == 0 or not inside[i, j] or d < lo or d > hi:
                continue
            if d == lo and drop_lo > 0:
                drop_lo -= 1
                continue
            if d == hi and drop_hi > 0:
                drop_hi -= 1
                continue
            z = d * units
            rx = np.float64(ray_x[i, j])
            ry = np.float64(ray_y[i, j])
            x = z * rx
            y = z * ry
            e = nx * x + ny * y + nz * z + d0
            dist[k] = e
            k += 1
            acc[0] += e * e
            if bf > 0:
                z_plane = -d0 / (nx * rx + ny * ry + nz)
                a = bf / z - bf / z_plane
                acc[1] += a * a
                px, py, pz = x - e * nx, y - e * ny, z - e * nz
                b = bf / np.sqrt(x * x + y * y + z * z) - bf / np.sqrt(px * px + py * py + pz * pz)
                acc[2] += b * b
    return k


def frame_metrics(raw: NDArray[np.uint16], inside: NDArray[np.bool_], ray_x: NDArray[np.floating],
                  ray_y: NDArray[np.floating], depth_units_m: float, roi_pixels: int, focal_px: float,
                  baseline_m: float | None, pivot_ray: F64, moments: F64 | None = None) -> DqtFrame:
    """The DQT's figures of one frame from a depth box, the ROI's pixels in it (`inside`), and the
    rays (x / z, y / z) of its pixels (h x w each, lens distortion inverted). `moments`: the valid
    points' 4x4 moment matrix about the camera (the study's, `kernels.board_moments`), computed
    here when not given."""
    out = DqtFrame(float("nan"), pivot_ray=(float(pivot_ray[0]), float(pivot_ray[1]), float(pivot_ray[2])))
    units = float(depth_units_m)
    if moments is None:
        moments = board_moments(raw, inside, np.zeros(inside.shape, np.uint8), ray_x.astype(np.float32),
                                ray_y.astype(np.float32), units, np.zeros(3))[1]["all"]
    n = round(float(moments[0, 0]))
    out.fill_rate_pct = 100.0 * n / roi_pixels if roi_pixels else float("nan")
    iu = np.triu_indices(3)  # xx, xy, xz, yy, yz, zz
    plane = plane_from_sums(n, moments[0, 1:], moments[1:, 1:][iu])
    if plane is None:
        return out
    normal, d0 = plane
    out.distance_mm = -d0 * 1000.0
    k = n // TRIM_DIVISOR  # the k nearest and k farthest in z leave (ties arbitrarily, as std::sort)
    lo, drop_lo, hi, drop_hi = 0, 0, 65535, 0
    if k:
        hist = np.zeros(65536, np.int64)
        _histogram(raw, inside, hist)
        lo, drop_lo, hi, drop_hi = _trim_bounds(hist, n, k)
    bf = float(baseline_m) * float(focal_px) if baseline_m else 0.0
    dist = np.empty(n, np.float64)
    acc = np.zeros(3)
    m = _residuals(raw, inside, ray_x, ray_y, units, float(normal[0]), float(normal[1]), float(normal[2]),
                   d0, lo, drop_lo, hi, drop_hi, bf, dist, acc)
    if m == 0:
        return out
    out.plane_fit_rms_mm = float(np.sqrt(acc[0] / m)) * 1000.0
    out.plane_fit_rms_pct = 100.0 * out.plane_fit_rms_mm / out.distance_mm
    if bf > 0:
        out.subpixel_rms_px = float(np.sqrt(acc[1] / m))
        out.subpixel_rms_tool_px = float(np.sqrt(acc[2] / m))
    denom = float(normal @ pivot_ray)
    if denom > 0:
        out.pivot_z_mm = -d0 / denom * float(pivot_ray[2]) * 1000.0
    dist = dist[:m]
    out.median_distance_mm = float(np.partition(dist, m // 2)[m // 2]) * 1000.0
    return out


@njit(cache=True, nogil=True)
def _pixel_ratios(samples: Any, scale: float, out: Any) -> None:  # pragma: no cover - compiled
    """Per pixel (row of `samples`, pixels x frames): std / median of its non-zero samples
    (population std; the median of an even count the mean of the middle two, as the DQT's); 0
    without samples. Insertion sort in place: at most 39 values."""
    n, f = samples.shape
    buf = np.empty(f, np.float64)
    for j in range(n):
        k = 0
        total = 0.0
        for i in range(f):
            v = samples[j, i]
            if v == 0:
                continue
            x = v * scale
            total += x
            m = k
            while m > 0 and buf[m - 1] > x:
                buf[m] = buf[m - 1]
                m -= 1
            buf[m] = x
            k += 1
        if k == 0:
            out[j] = 0.0
            continue
        med = buf[k // 2] if k % 2 else 0.5 * (buf[k // 2 - 1] + buf[k // 2])
        mean = total / k
        var = 0.0
        for i in range(k):
            var += (buf[i] - mean) ** 2
        out[j] = np.sqrt(var / k) / med if med > 0 else 0.0


def temporal_noise_pct(stack: NDArray[np.uint16], depth_units_m: float) -> float:
    """DQT temporal noise of frames x pixels raw depth (0 = none): median over pixels of std /
    median over frames, pixels without any depth counting as 0."""
    if stack.shape[0] < 2 or stack.shape[1] == 0:
        return float("nan")
    ratios = np.empty(stack.shape[1], np.float64)
    _pixel_ratios(np.ascontiguousarray(stack.T), float(depth_units_m) * 1000.0, ratios)
    return float(100.0 * np.median(ratios))


def expected_rms_mm(distance_mm: float, focal_px: float, baseline_m: float | None,
                    subpixel_px: float = EXPECTED_SUBPIXEL_PX) -> float:
    """Intel's expected depth RMS error (mm) at a distance: Z^2 * subpixel / (f * B)."""
    if not baseline_m or not np.isfinite(distance_mm) or focal_px <= 0:
        return float("nan")
    return float(distance_mm**2 * subpixel_px / (focal_px * float(baseline_m) * 1000.0))


class TemporalStack:
    """The raw depth of one fixed pixel set over the first frames of a standpoint."""

    def __init__(self, frames: int = TEMPORAL_FRAMES) -> None:
        self.frames = frames
        self.rows: NDArray[np.intp] | None = None
        self.cols: NDArray[np.intp] | None = None
        self.samples: list[NDArray[np.uint16]] = []

    def start(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> None:
        """The pixel set (the first frame's), kept for the rest."""
        self.rows, self.cols = rows, cols

    def add(self, depth: NDArray[np.uint16]) -> None:
        """One frame's raw depth at the pixel set (up to `frames` frames)."""
        if self.rows is not None and self.cols is not None and len(self.samples) < self.frames:
            self.samples.append(np.asarray(depth[self.rows, self.cols]))

    def noise_pct(self, depth_units_m: float) -> float:
        if not self.samples:
            return float("nan")
        return temporal_noise_pct(np.stack(self.samples), depth_units_m)


def standpoint_figures(frames: list[DqtFrame], ground_truth_mm: list[float], temporal_pct: float,
                       focal_px: float, baseline_m: float | None, prefix: str) -> dict[str, float]:
    """Mean over frames of each DQT figure, Z accuracy against each frame's ground truth, the
    temporal noise, Intel's expected RMS at the mean distance and measured / expected."""
    def mean(values: list[float]) -> float:
        a = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
        return float(a.mean()) if a.size else float("nan")

    f = {
        "fill_rate_pct": mean([x.fill_rate_pct for x in frames]),
        "distance_mm": mean([x.distance_mm for x in frames]),
        "plane_fit_rms_mm": mean([x.plane_fit_rms_mm for x in frames]),
        "plane_fit_rms_pct": mean([x.plane_fit_rms_pct for x in frames]),
        "subpixel_rms_px": mean([x.subpixel_rms_px for x in frames]),
        "subpixel_rms_tool_px": mean([x.subpixel_rms_tool_px for x in frames]),
        "z_accuracy_pct": mean([x.z_accuracy_pct(g) for x, g in zip(frames, ground_truth_mm, strict=True)]),
        "temporal_noise_pct": temporal_pct,
    }
    f["expected_rms_mm"] = expected_rms_mm(f["distance_mm"], focal_px, baseline_m)
    f["rms_ratio"] = (f["plane_fit_rms_mm"] / f["expected_rms_mm"]
                      if np.isfinite(f["expected_rms_mm"]) and f["expected_rms_mm"] > 0 else float("nan"))
    return {f"{prefix}{k}": v for k, v in f.items()}
