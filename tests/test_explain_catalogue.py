"""Catalogue first: a catalogue effect the data select is kept unless generic terms do better on
held-out standpoints AND it loses its significance beside them; every keep and drop says why.

Tables written here (not by `tables.py`): 18 standpoints x 15 frames of tiles, the residual a z^2
disparity offset (the catalogue's `disparity_offset` column -K) or a term of another shape, plus
white noise. The generic stand-in is a quadratic in time within the standpoint (a proxy of the
frame's position), the term that took the place of a real offset on a blind case.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from depthstation.evaluate.explain.discover import TableResult, _catalogue_holds
from depthstation.evaluate.explain.mixed_model import bic
from depthstation.evaluate.explain.tables import Table

FB = 640.0 * 0.095   # f B of a D455-like camera at 640 px (px m)


def _table(truth: str, seed: int = 0) -> Table:
    rng = np.random.default_rng(seed)
    sp = np.repeat(np.arange(18), 15 * 6)                       # 18 standpoints x 15 frames x 6 tiles
    frame = np.tile(np.repeat(np.arange(15), 6), 18)
    z = np.repeat(np.linspace(1.0, 4.0, 6), 3)[sp]             # 1-4 m, three inclinations each
    k_m = z ** 2 / FB                                          # m of depth per px of disparity
    t = frame / 30.0                                           # s within the standpoint (0-0.47 s)
    tc = t - np.median(t)
    X = {"disparity_offset": (-k_m)[:, None],
         "term_bias_time_poly2": np.stack([-k_m * tc, -k_m * tc ** 2], axis=1)}
    delta = 0.045 if truth == "offset" else 1.4 * tc ** 2       # px
    y = -k_m * delta + 2e-4 * rng.standard_normal(sp.size)
    return Table("bias", y, np.ones(sp.size), X, cluster=sp, fold=sp, standpoint=sp, name="bias")


def _path(t: Table, names: list[str]) -> Any:
    terms = [SimpleNamespace(effect=n, axes=["time"]) for n in names if n.startswith("term_")]
    return TableResult(names, terms, {}, [], [], bic(t, names))   # type: ignore[arg-type]


def test_a_selected_offset_is_kept_against_a_time_proxy() -> None:
    t = _table("offset")
    seq, uni = _path(t, ["disparity_offset"]), _path(t, ["term_bias_time_poly2"])
    why = _catalogue_holds(t, seq, uni, ["disparity_offset"])
    assert why, "the catalogue's offset must stand"
    assert "held-out" in why or "stays significant" in why


def test_a_generic_term_that_truly_is_better_replaces_the_catalogue() -> None:
    """Where the residual is the time term itself, the offset that approximated it goes."""
    t = _table("time")
    seq, uni = _path(t, ["disparity_offset"]), _path(t, ["term_bias_time_poly2"])
    assert uni.bic < seq.bic
    assert _catalogue_holds(t, seq, uni, ["disparity_offset"]) == ""
