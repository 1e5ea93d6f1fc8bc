"""Pinhole camera model, extrinsics and the librealsense pixel conventions (pixel centres at integers)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# Lens models whose coefficients are OpenCV's distortion vector (k1 k2 p1 p2 k3 [k4 k5 k6 ...]):
# librealsense's Brown-Conrady variants, ROS's plumb_bob and rational_polynomial, OpenCV's own.
OPENCV_MODELS = ("brown_conrady", "inverse_brown_conrady", "modified_brown_conrady", "opencv",
                 "plumb_bob", "rational_polynomial")
OPENCV_LENGTHS = (4, 5, 8, 12, 14)  # the distortion vector lengths OpenCV takes
# OpenCV's default five steps leave pixels off by up to ~5 px for an 8-coefficient lens
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def model_name(name: str) -> str:
    """Our spelling of a lens model: librealsense's ('Inverse Brown Conrady',
    'distortion.brown_conrady') and ROS's ('plumb_bob', 'equidistant') normalised, so that a file
    written with either is read, not refused or dropped."""
    n = str(name).split(".")[-1].strip().lower().replace(" ", "_").replace("-", "_")
    return {"plumb_bob": "brown_conrady", "equidistant": "kannala_brandt4", "": "none"}.get(n, n)


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics of one stream as librealsense reports them (pixels, distortion model name)."""

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    model: str = "none"
    coeffs: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> FloatArray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.ppx], [0.0, self.fy, self.ppy], [0.0, 0.0, 1.0]])

    def opencv_distortion(self) -> FloatArray:
        """OpenCV's distortion vector for this record (zeros for 'none' or unknown models).

        librealsense's Brown-Conrady variants (including `inverse_brown_conrady`, which
        `rs2_project_point_to_pixel` applies forward) are OpenCV's k1 k2 p1 p2 k3.
        """
        if model_name(self.model) in OPENCV_MODELS and any(c != 0.0 for c in self.coeffs):
            return np.asarray(self.coeffs, dtype=np.float64)
        return np.zeros(5)

    def lens_problem(self) -> str | None:
        """Why the station cannot invert this lens (None when it can): a model OpenCV does not
        know, or a coefficient count it does not take, with non-zero coefficients. Dropping such
        a distortion would put every pixel on the wrong ray without a word."""
        model = model_name(self.model)
        if not any(c != 0.0 for c in self.coeffs) or model == "none":
            return None
        if model not in OPENCV_MODELS:
            return (f"lens model {self.model!r} with non-zero coefficients: the station inverts "
                    "Brown-Conrady (plumb_bob) and rational_polynomial lenses; rectify the images first")
        if len(self.coeffs) not in OPENCV_LENGTHS:
            return (f"lens model {self.model!r} with {len(self.coeffs)} coefficients (OpenCV takes "
                    f"{', '.join(map(str, OPENCV_LENGTHS))})")
        return None

    @property
    def has_distortion(self) -> bool:
        """Whether the lens model bends rays (a model OpenCV knows, with a non-zero coefficient)."""
        return bool(np.any(self.opencv_distortion() != 0.0))

    def pinhole(self) -> Intrinsics:
        """The same camera matrix without lens distortion."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.ppx, self.ppy)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Same optics at another resolution (how the D4xx derive 848x480 etc. from 1280x720)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy,
                          (self.ppx + 0.5) * sx - 0.5, (self.ppy + 0.5) * sy - 0.5,
                          self.model, self.coeffs)

    def to_dict(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "ppx": self.ppx, "ppy": self.ppy, "model": self.model, "coeffs": list(self.coeffs)}

    def check(self) -> Intrinsics:
        """Raise ValueError naming the field when the record has no physical meaning."""
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"width and height must be positive, got {self.width}x{self.height}")
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a positive focal length in pixels, got {v}")
        for name, size in (("ppx", self.width), ("ppy", self.height)):
            v = getattr(self, name)
            if not math.isfinite(v) or not -0.5 <= v <= size - 0.5:
                raise ValueError(f"{name} must lie in the image (0 to {size - 1} px), got {v}")
        if not all(math.isfinite(c) for c in self.coeffs):
            raise ValueError("distortion coefficients must be finite")
        return self

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Intrinsics:
        """Accepts our keys and the `cx`/`cy`/`distortion` spelling of camera.json files; raises
        KeyError for a missing key and ValueError for a value without physical meaning.

        Coefficients without a `model` are OpenCV's k1 k2 p1 p2 k3 [k4 k5 k6] (what calibration
        tools write): before, they were read as no lens at all and silently dropped."""
        ppx = d["ppx"] if "ppx" in d else d["cx"]
        ppy = d["ppy"] if "ppy" in d else d["cy"]
        coeffs = tuple(float(c) for c in d.get("coeffs", d.get("distortion", [0.0] * 5)))
        model = d.get("model", "opencv" if any(c != 0.0 for c in coeffs) else "none")
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                   float(ppx), float(ppy), model_name(str(model)), coeffs).check()


@dataclass(frozen=True)
class Extrinsics:
    """Rigid transform from frame A to frame B: p_B = R @ p_A + t (metres). R stored row-major."""

    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def R(self) -> FloatArray:
        return np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)

    @property
    def t(self) -> FloatArray:
        return np.asarray(self.translation, dtype=np.float64)

    @property
    def matrix(self) -> FloatArray:
        """4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @classmethod
    def from_matrix(cls, m: NDArray[Any]) -> Extrinsics:
        m = np.asarray(m, dtype=np.float64)
        return cls(tuple(float(x) for x in m[:3, :3].ravel()),
                   (float(m[0, 3]), float(m[1, 3]), float(m[2, 3])))

    @classmethod
    def from_librealsense(cls, rotation: Any, translation: Any) -> Extrinsics:
        """librealsense stores the rotation column-major; this turns it into our row-major R."""
        r = np.asarray(list(rotation), dtype=np.float64).reshape(3, 3).T
        return cls(tuple(float(x) for x in r.ravel()), tuple(float(x) for x in translation))  # type: ignore[arg-type]

    def to_librealsense(self) -> tuple[list[float], list[float]]:
        return [float(x) for x in self.R.T.ravel()], [float(x) for x in self.t]

    def inverse(self) -> Extrinsics:
        return Extrinsics.from_matrix(np.linalg.inv(self.matrix))

    def apply(self, points: NDArray[Any]) -> FloatArray:
        """Transform Nx3 points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def to_dict(self) -> dict[str, Any]:
        return {"rotation": list(self.rotation), "translation": list(self.translation)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Extrinsics:
        return cls(tuple(float(x) for x in d["rotation"]),
                   tuple(float(x) for x in d["translation"]))  # type: ignore[arg-type]


def pixel_grid(intr: Intrinsics) -> tuple[FloatArray, FloatArray]:
    """Integer pixel-centre coordinates (u, v), each HxW float64 (librealsense convention)."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    return u, v


def pixel_rays(intr: Intrinsics) -> NDArray[np.float32]:
    """HxWx3 camera-frame ray directions with z = 1 through every pixel centre.

    The one ray builder of the station (the simulator's views, the scan study's casts): integer
    pixel centres (librealsense), and a lens distortion, when the stream reports one, inverted
    so that each ray meets the point the lens imaged at that pixel (`ray_planes`). The z = 1
    directions make a ray's hit parameter the z-depth itself.
    """
    x, y = ray_planes(intr)
    d = np.empty((intr.height, intr.width, 3), dtype=np.float32)
    d[..., 0] = x
    d[..., 1] = y
    d[..., 2] = 1.0
    return d


@lru_cache(maxsize=8)
def ray_planes(intr: Intrinsics) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """x / z and y / z of the ray through every pixel centre (two read-only H x W arrays).

    A pinhole's are a column and a row broadcast (no memory). With lens distortion the lens
    model is inverted with OpenCV, iterated to 1e-12 (its default five steps leave pixels off by
    up to ~5 px for an 8-coefficient lens); cached, as it takes ~0.3 s for 1280x720.
    """
    h, w = intr.height, intr.width
    dist = intr.opencv_distortion()
    if np.any(dist != 0.0):
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        pts = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
        # OpenCV 4 names the iterated form undistortPointsIter; OpenCV 5 gives undistortPoints the criteria
        iterated = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)
        und = iterated(pts, intr.K, dist, R=np.eye(3), P=np.eye(3),
                       criteria=_UNDISTORT_CRITERIA).reshape(h, w, 2)
        x = np.ascontiguousarray(und[..., 0], dtype=np.float64)
        y = np.ascontiguousarray(und[..., 1], dtype=np.float64)
        x.flags.writeable = False
        y.flags.writeable = False
        return x, y
    col = (np.arange(w, dtype=np.float64) - intr.ppx) / intr.fx
    row = (np.arange(h, dtype=np.float64) - intr.ppy) / intr.fy
    return np.broadcast_to(col[None, :], (h, w)), np.broadcast_to(row[:, None], (h, w))


def ray_xy(intr: Intrinsics, u: NDArray[Any], v: NDArray[Any]) -> tuple[FloatArray, FloatArray]:
    """x / z and y / z of the rays through integer pixels (u, v), lens distortion inverted."""
    x, y = ray_planes(intr)
    ui, vi = np.asarray(u, dtype=np.intp), np.asarray(v, dtype=np.intp)
    return x[vi, ui], y[vi, ui]


def deproject(intr: Intrinsics, u: NDArray[Any], v: NDArray[Any], z: NDArray[Any]) -> FloatArray:
    """Pixels (u, v) with z-depth z (metres) to Nx3 camera points, like rs2_deproject_pixel_to_point."""
    x = (np.asarray(u, dtype=np.float64) - intr.ppx) / intr.fx
    y = (np.asarray(v, dtype=np.float64) - intr.ppy) / intr.fy
    z = np.asarray(z, dtype=np.float64)
    return np.stack([x * z, y * z, z], axis=-1)


def project(intr: Intrinsics, points: NDArray[Any]) -> FloatArray:
    """Nx3 camera points to Nx2 pixel coordinates (no distortion)."""
    p = np.asarray(points, dtype=np.float64)
    z = p[..., 2]
    return np.stack([p[..., 0] / z * intr.fx + intr.ppx, p[..., 1] / z * intr.fy + intr.ppy], axis=-1)


@dataclass(frozen=True)
class StreamInfo:
    """What a recording or camera delivers: stream geometry, depth scale and the device."""

    depth_intrinsics: Intrinsics
    color_intrinsics: Intrinsics | None
    depth_to_color: Extrinsics = field(default_factory=Extrinsics)
    depth_units_m: float = 0.001
    depth_aligned_to_color: bool = False
    infrared_intrinsics: Intrinsics | None = None
    baseline_m: float | None = None
    fps: float | None = None
    device: dict[str, Any] = field(default_factory=dict)
    stereo_intrinsics: Intrinsics | None = None

    @property
    def stereo(self) -> Intrinsics:
        """The depth imager's own intrinsics, where disparity lives.

        When depth was aligned to another camera (rs.align), `depth_intrinsics` are that camera's
        and a pixel of disparity is a pixel of the stereo imager, not of the aligned image:
        `stereo_intrinsics` then holds the imager's own; otherwise they are the depth stream's.
        """
        return self.stereo_intrinsics if self.stereo_intrinsics is not None else self.depth_intrinsics

    def to_stereo_pixels(self, u: NDArray[Any], v: NDArray[Any]) -> tuple[FloatArray, FloatArray]:
        """Depth-pixel coordinates in the stereo imager's pixels (same ray, its focal length)."""
        d, s = self.depth_intrinsics, self.stereo
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        if s is d:
            return u, v
        if d.has_distortion:   # depth aligned to a camera with a lens: the pixel's ray through it
            x, y = ray_xy(d, np.rint(u), np.rint(v))
            return s.ppx + x * s.fx, s.ppy + y * s.fy
        return s.ppx + (u - d.ppx) * (s.fx / d.fx), s.ppy + (v - d.ppy) * (s.fy / d.fy)

    def to_dict(self) -> dict[str, Any]:
        return {
            "depth_intrinsics": self.depth_intrinsics.to_dict(),
            "color_intrinsics": None if self.color_intrinsics is None else self.color_intrinsics.to_dict(),
            "infrared_intrinsics": (None if self.infrared_intrinsics is None
                                    else self.infrared_intrinsics.to_dict()),
            "depth_to_color": self.depth_to_color.to_dict(),
            "depth_units_m": self.depth_units_m,
            "depth_aligned_to_color": self.depth_aligned_to_color,
            "baseline_m": self.baseline_m,
            "fps": self.fps,
            "device": dict(self.device),
            "stereo_intrinsics": (None if self.stereo_intrinsics is None
                                  else self.stereo_intrinsics.to_dict()),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StreamInfo:
        ci = d.get("color_intrinsics")
        ii = d.get("infrared_intrinsics")
        si = d.get("stereo_intrinsics")
        return cls(
            depth_intrinsics=Intrinsics.from_dict(d["depth_intrinsics"]),
            color_intrinsics=None if ci is None else Intrinsics.from_dict(ci),
            depth_to_color=Extrinsics.from_dict(d.get("depth_to_color", Extrinsics().to_dict())),
            depth_units_m=float(d.get("depth_units_m", 0.001)),
            depth_aligned_to_color=bool(d.get("depth_aligned_to_color", False)),
            infrared_intrinsics=None if ii is None else Intrinsics.from_dict(ii),
            baseline_m=None if d.get("baseline_m") is None else float(d["baseline_m"]),
            fps=None if d.get("fps") is None else float(d["fps"]),
            device=dict(d.get("device", {})),
            stereo_intrinsics=None if si is None else Intrinsics.from_dict(si),
        )
