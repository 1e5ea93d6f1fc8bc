"""Acquisition: camera backends (live, playback, simulated), warm-up, calibration, guided capture."""

from depthstation.core.stage_folder import claim_stage

claim_stage(__name__, __file__)
