"""A camera's depth error model: fitted to its studies (`model fit`), shown (`model show`), and
applied to a recording (`correct`): bias removed per pixel, sigma per pixel for SLAM / TSDF weights.

Public entry points: `fit_model` (result folders -> ErrorModel), `load_model`, `correct_recording`.
"""

from depthstation.evaluate.errormodel.build import fit_model
from depthstation.evaluate.errormodel.correct import correct_recording
from depthstation.evaluate.errormodel.schema import SCHEMA_VERSION, ErrorModel, load_model

__all__ = ["SCHEMA_VERSION", "ErrorModel", "correct_recording", "fit_model", "load_model"]
