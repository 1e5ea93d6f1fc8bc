"""Acquisition: camera backends (live, playback, simulated), warm-up, calibration, guided capture."""
