"""Evaluation: readers of captures into studies: checkerboard, reference scan, explain."""

from depthstation.core.stage_folder import claim_stage

claim_stage(__name__, __file__)
