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
from depthstation.evaluate.explain.library import library
from depthstation.evaluate.explain.locate import default_groups
from depthstation.evaluate.explain.mixed_model import bic
from depthstation.evaluate.explain.samples import Samples, concat, session_clock, without_clock
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


def _samples(stamps_ns: list[list[int]]) -> Samples:
    """One small board per standpoint, its frames at the given stamps (written here, not read)."""
    rng = np.random.default_rng(3)
    parts = []
    names = [f"sp{k}" for k in range(len(stamps_ns))]
    v, u = np.mgrid[40:80, 60:120].astype(float)
    t0 = min(min(s) for s in stamps_ns)
    for k, stamps in enumerate(stamps_ns):
        for i, ts in enumerate(stamps):
            parts.append(Samples.build(
                names=names, fx=200.0, ppx=80.0, ppy=60.0, baseline_m=0.095, standpoint=k, frame=i, u=u, v=v,
                z_ref_m=1.0 + 0.5 * k, err_m=1e-3 * rng.standard_normal(u.size), inclination_deg=10.0 * k,
                albedo=np.where(u % 20 < 10, 0.05, 0.85), time_s=(ts - t0) / 1e9))
    return concat(parts)


def test_frames_without_a_session_clock_get_no_time_axis() -> None:
    """PNG folders stamp k / fps from 0 in every standpoint; bags restarting their stamps overlap:
    neither is a clock of the session, so no locate family and no library term runs along time."""
    png = [[round(i * 1e9 / 30) for i in range(5)] for _ in range(4)]
    session = [[1_700_000_000_000_000_000 + k * 60_000_000_000 + round(i * 1e9 / 30) for i in range(5)]
               for k in range(4)]
    restarting = [[1_700_000_000_000_000_000 + round(i * 1e9 / 30) + k for i in range(5)] for k in range(4)]
    assert not session_clock(png) and not session_clock(restarting) and session_clock(session)
    timed = _samples(session)
    bare = without_clock(_samples(png))
    assert not bare.time_stamps and not np.any(bare.time_s)
    assert "time" in {g.family for g in default_groups(timed, timed)}
    assert "time" not in {g.family for g in default_groups(bare, bare)}
    assert any("time" in (c.spec.axes if c.spec else ()) for c in library(timed))
    assert not any("time" in (c.spec.axes if c.spec else ()) for c in library(bare))
    assert concat([bare, bare]).time_stamps is False
