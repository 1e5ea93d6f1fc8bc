"""Simulated RealSense D455: scenes, ray casting, sensor effects, rendering into captures."""

from depthstation.core.stage_folder import claim_stage

claim_stage(__name__, __file__)
