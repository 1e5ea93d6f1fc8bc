"""`model fit`'s work: result folders in, one ErrorModel out (the measured table, the domain, both
fitted parts, the camera and the inputs)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import InputError
from depthstation.core.results import COMMAND_LINE, software_versions
from depthstation.evaluate.errormodel.fit import fit_part, stack
from depthstation.evaluate.errormodel.inputs import input_record, one_camera, read_result
from depthstation.evaluate.errormodel.schema import Domain, ErrorModel


def fit_model(results: Sequence[Path], *, distance_bin_m: float = 0.1, inclination_bin_deg: float = 5.0,
              min_count: int = 200) -> ErrorModel:
    """The error model of the camera the result folders measured."""
    if not results:
        raise InputError(None, "give at least one result folder (a scan or checkerboard study)")
    if distance_bin_m <= 0 or inclination_bin_deg <= 0:
        raise InputError(None, "--distance-bin-m and --inclination-bin-deg must be positive")
    fields = [read_result(Path(p), distance_bin_m, inclination_bin_deg, min_count) for p in results]
    seen: dict[Path, Path] = {}
    for f in fields:
        key = f.path.resolve()
        if key in seen:
            raise InputError(f.path, "is given twice: its cells would count twice")
        seen[key] = f.path
    camera = one_camera(fields)
    bias_rows, sigma_rows = stack(fields, "mean"), stack(fields, "std")
    if len(bias_rows.y) < 2:
        raise InputError(fields[0].path, f"{len(bias_rows.y)} usable cell(s) or standpoint(s): too few "
                                         "to fit a model (at least 2)")
    try:
        bias = fit_part(bias_rows, name="bias")
        sigma = fit_part(sigma_rows, name="sigma")
    except ValueError as exc:
        raise InputError(fields[0].path, str(exc)) from exc
    boxes = np.concatenate([f.domain_boxes() for f in fields])
    rows: list[dict[str, Any]] = [r for f in fields for r in f.rows()]
    measured = {"columns": {"distance_m": "cell centre or standpoint distance (z-depth, m)",
                            "distance_lo_m / distance_hi_m":
                                "the cell's (or the standpoint's domain) distance span",
                            "inclination_deg": "cell centre or standpoint inclination (deg)",
                            "count": "samples in the cell (pixels), or frames of the standpoint",
                            "mean_m": "mean depth error, measured - reference z-depth (+ = too far)",
                            "std_m": "standard deviation of the depth error (the table cell's bias "
                                     "variation within it included)",
                            "u95_m": "expanded uncertainty (95 %) of mean_m",
                            "se_m": "standard error of mean_m (the fit's weight is 1 / se_m^2)"},
                "rows": rows}
    extra = {"created_by": {"command_line": COMMAND_LINE.get(), "software": software_versions()},
             "fit_options": {"distance_bin_m": distance_bin_m, "inclination_bin_deg": inclination_bin_deg,
                             "min_count": min_count},
             "notes": [n for f in fields for n in f.notes]}
    return ErrorModel(camera, bias, sigma, Domain(boxes), measured, [input_record(f) for f in fields], extra)
