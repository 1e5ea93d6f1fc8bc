"""The error model's file: a versioned JSON document (docs/results.md, "Depth error model") and its
evaluation b(z, theta), sigma(z, theta) with the validity domain.

Why a parametric model and not the measured field alone: a mapping pipeline needs a bias to
subtract and a standard deviation at every depth and inclination it meets, smooth and cheap to
evaluate per pixel; the measured field is kept beside it (`measured`) so a user can see what the
model stands on, and the domain says where it was measured. Outside the domain the model gives
NaN and `inside` False: it never extrapolates silently.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.errors import InputError

SCHEMA_NAME = "depthstation-error-model"
SCHEMA_VERSION = 1

# The candidate terms of b and sigma, in this order everywhere (coefficient vectors, kernels).
# z in metres, theta the inclination (ray vs surface normal). Physical reading:
#   offset      c                  a constant depth offset (the depth unit's zero, a housing offset)
#   scale       c z                a depth-scale error (baseline or focal length off by a fraction)
#   disparity   c z^2              a constant disparity error d0: dz = z^2 d0 / (f B) (stereo's z^2 law)
#   incl_scale  c z tan(theta)     a matching window on a slanted surface, in proportion to z
#   inclination c z^2 tan(theta)   the disparity error growing with the slant (window foreshortening)
TERMS = ("offset", "scale", "disparity", "incl_scale", "inclination")
TERM_FORMULAS = {"offset": "1", "scale": "z", "disparity": "z^2", "incl_scale": "z tan(theta)",
                 "inclination": "z^2 tan(theta)"}
THETA_TERMS = frozenset({"incl_scale", "inclination"})
# tan(theta) is capped here: beyond ~85 deg a stereo camera measures next to nothing, and the
# domain never reaches it in practice; the cap only keeps an evaluation finite
THETA_CAP_DEG = 85.0
# the domain raster `correct` looks pixels up in (fine enough to follow any table's cells)
RASTER_Z_STEP_M = 0.005
RASTER_THETA_STEP_DEG = 0.5
RASTER_COS_STEPS = 2048          # 0.03 deg at 10 deg, 0.005 deg at 70 deg

F64 = NDArray[np.float64]


def design(z: Any, theta_deg: Any, terms: tuple[str, ...] = TERMS) -> F64:
    """The basis functions of `terms` at (z, theta): an N x len(terms) matrix."""
    z = np.asarray(z, dtype=np.float64).ravel()
    t = np.tan(np.radians(np.minimum(np.asarray(theta_deg, dtype=np.float64).ravel(), THETA_CAP_DEG)))
    cols = {"offset": np.ones_like(z), "scale": z, "disparity": z * z, "incl_scale": z * t,
            "inclination": z * z * t}
    return np.stack([cols[k] for k in terms], axis=-1) if terms else np.zeros((z.size, 0))


@dataclass
class Part:
    """One fitted quantity (bias or sigma): its selected terms, coefficients and their covariance."""

    terms: tuple[str, ...]
    coefficients: F64
    covariance: F64
    info: dict[str, Any] = field(default_factory=dict)   # selection, validation, fit statistics

    def full(self) -> F64:
        """Coefficients over all of TERMS (zeros for the terms not selected)."""
        out = np.zeros(len(TERMS))
        for k, c in zip(self.terms, self.coefficients, strict=True):
            out[TERMS.index(k)] = c
        return out

    def value(self, z: Any, theta_deg: Any) -> F64:
        return design(z, theta_deg, self.terms) @ self.coefficients

    def std_error(self, z: Any, theta_deg: Any) -> F64:
        """Standard error of the model's value (the coefficients' covariance propagated)."""
        x = design(z, theta_deg, self.terms)
        return np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", x, self.covariance, x), 0.0))

    def to_dict(self) -> dict[str, Any]:
        se = np.sqrt(np.maximum(np.diag(self.covariance), 0.0)) if len(self.terms) else np.zeros(0)
        return {"terms": list(self.terms),
                "formulas": [TERM_FORMULAS[k] for k in self.terms],
                "coefficients": [float(c) for c in self.coefficients],
                "std_errors": [float(s) for s in se],
                "covariance": [[float(v) for v in row] for row in self.covariance],
                **self.info}

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: Path, key: str) -> Part:
        try:
            terms = tuple(str(t) for t in d["terms"])
            coef = np.asarray(d["coefficients"], dtype=np.float64).reshape(len(terms))
            cov = np.asarray(d["covariance"], dtype=np.float64).reshape(len(terms), len(terms))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"'{key}' is no model part (terms, coefficients, covariance): "
                                   f"{exc}") from exc
        unknown = [t for t in terms if t not in TERMS]
        if unknown:
            raise InputError(path, f"'{key}.terms' names unknown terms {unknown}; known: {', '.join(TERMS)}")
        if not np.all(np.isfinite(coef)):
            raise InputError(path, f"'{key}.coefficients' holds a value that is no finite number")
        info = {k: v for k, v in d.items() if k not in ("terms", "formulas", "coefficients", "std_errors",
                                                          "covariance")}
        return cls(terms, coef, cov, info)


@dataclass
class Domain:
    """Where the model was measured: boxes [z_lo, z_hi) x [theta_lo, theta_hi) (the table's cells
    with enough samples, or a checkerboard study's span of standpoints)."""

    boxes: F64  # K x 4: z_lo, z_hi, theta_lo, theta_hi

    def contains(self, z: Any, theta_deg: Any) -> NDArray[np.bool_]:
        z = np.asarray(z, dtype=np.float64)
        t = np.asarray(theta_deg, dtype=np.float64)
        inside = np.zeros(np.broadcast(z, t).shape, dtype=bool)
        for z0, z1, t0, t1 in self.boxes:
            inside |= (z >= z0) & (z < z1) & (t >= t0) & (t < t1)
        return inside

    def raster(self) -> tuple[NDArray[np.uint8], float, float]:
        """The domain as a lookup raster over (z / RASTER_Z_STEP_M, theta / RASTER_THETA_STEP_DEG):
        a cell of the raster is inside when its centre is (what `correct`'s kernel reads)."""
        zmax = float(self.boxes[:, 1].max()) if len(self.boxes) else 0.0
        nz = math.ceil(zmax / RASTER_Z_STEP_M) + 1
        nt = math.ceil(90.0 / RASTER_THETA_STEP_DEG) + 1
        zc = (np.arange(nz) + 0.5) * RASTER_Z_STEP_M
        tc = (np.arange(nt) + 0.5) * RASTER_THETA_STEP_DEG
        r = self.contains(zc[:, None], tc[None, :]).astype(np.uint8)
        return r, RASTER_Z_STEP_M, RASTER_THETA_STEP_DEG

    def cos_raster(self) -> tuple[NDArray[np.uint8], float, int]:
        """The domain as a lookup raster over (z / RASTER_Z_STEP_M, cos(theta) x RASTER_COS_STEPS)
        (`correct`'s kernel has cos(theta) per pixel: no arccos per pixel). A raster cell is inside
        when its centre is."""
        zmax = float(self.boxes[:, 1].max()) if len(self.boxes) else 0.0
        nz = math.ceil(zmax / RASTER_Z_STEP_M) + 1
        zc = (np.arange(nz) + 0.5) * RASTER_Z_STEP_M
        cc = (np.arange(RASTER_COS_STEPS) + 0.5) / RASTER_COS_STEPS
        tc = np.degrees(np.arccos(cc))
        r = self.contains(zc[:, None], tc[None, :]).astype(np.uint8)
        return r, RASTER_Z_STEP_M, RASTER_COS_STEPS

    @property
    def z_range_m(self) -> tuple[float, float]:
        return float(self.boxes[:, 0].min()), float(self.boxes[:, 1].max())

    @property
    def theta_range_deg(self) -> tuple[float, float]:
        return float(self.boxes[:, 2].min()), float(self.boxes[:, 3].max())

    def to_dict(self) -> dict[str, Any]:
        return {"boxes": [[float(v) for v in b] for b in self.boxes],
                "columns": ["distance_lo_m", "distance_hi_m", "inclination_lo_deg", "inclination_hi_deg"],
                "distance_range_m": list(self.z_range_m), "inclination_range_deg": list(self.theta_range_deg)}


@dataclass
class ErrorModel:
    """A camera's depth error model: bias and sigma over (z, theta), the domain, the measured
    field and where it came from."""

    camera: dict[str, Any]
    bias: Part
    sigma: Part
    domain: Domain
    measured: dict[str, Any]
    inputs: list[dict[str, Any]]
    extra: dict[str, Any] = field(default_factory=dict)

    def evaluate(self, z: Any, theta_deg: Any) -> tuple[F64, F64, NDArray[np.bool_]]:
        """(bias m, sigma m, inside) at reference z-depth z (m) and inclination theta (deg); NaN
        outside the domain (the model does not extrapolate)."""
        z = np.asarray(z, dtype=np.float64)
        t = np.asarray(theta_deg, dtype=np.float64)
        zb, tb = np.broadcast_arrays(z, t)
        inside = self.domain.contains(zb, tb)
        b = self.bias.value(zb, tb).reshape(zb.shape)
        s = self.sigma.value(zb, tb).reshape(zb.shape)
        return np.where(inside, b, np.nan), np.where(inside, s, np.nan), inside

    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION,
                **self.extra,
                "camera": self.camera, "inputs": self.inputs,
                "terms": {k: TERM_FORMULAS[k] for k in TERMS},
                "units": "z and bias, sigma in metres; theta in degrees; bias = measured - reference "
                         "z-depth (+ = too far)",
                "bias": self.bias.to_dict(), "sigma": self.sigma.to_dict(),
                "domain": self.domain.to_dict(), "measured": self.measured}


def load_model(path: Path) -> ErrorModel:
    """Read and check a model file; bad input names the file and the key (exit 2)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise InputError(path, "does not exist") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot be read ({exc})") from exc
    except json.JSONDecodeError as exc:
        raise InputError(path, f"is no JSON document ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA_NAME:
        raise InputError(path, f"is no depth error model ('schema' is not {SCHEMA_NAME!r})")
    version = doc.get("schema_version")
    if version != SCHEMA_VERSION:
        raise InputError(path, f"'schema_version' is {version!r}; this depthstation reads version "
                               f"{SCHEMA_VERSION} (fit the model again with this version)")
    for key in ("camera", "bias", "sigma", "domain", "measured", "inputs"):
        if key not in doc:
            raise InputError(path, f"has no '{key}'")
    try:
        boxes = np.asarray(doc["domain"]["boxes"], dtype=np.float64).reshape(-1, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, "'domain.boxes' is no list of [z_lo, z_hi, theta_lo, theta_hi]: "
                               f"{exc}") from exc
    if len(boxes) == 0:
        raise InputError(path, "'domain.boxes' is empty: the model was measured nowhere")
    if not isinstance(doc["camera"], dict):
        raise InputError(path, "'camera' is no object")
    known = ("schema", "schema_version", "camera", "inputs", "terms", "units", "bias", "sigma", "domain",
             "measured")
    extra = {k: v for k, v in doc.items() if k not in known}
    return ErrorModel(doc["camera"], Part.from_dict(doc["bias"], path, "bias"),
                      Part.from_dict(doc["sigma"], path, "sigma"), Domain(boxes), doc["measured"],
                      list(doc["inputs"]), extra)
