"""Evaluation: readers of captures into studies: checkerboard, reference scan, explain."""
