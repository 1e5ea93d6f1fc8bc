"""The explain result in rerun: the summary text and real-minus-sim mean error along each axis."""

from __future__ import annotations

from typing import Any

from depthstation.viz import RerunTarget, recording
from evaluate.explain.pipeline import Explanation


def log_explanation(ex: Explanation, target: RerunTarget) -> None:
    import rerun as rr

    sel = ", ".join(c.effect for c in ex.attribution.selected) or "nothing"
    desc = (f"# depthstation explain\nSelected: {sel}.\nSeries: mean z error real - sim (mm) per group, "
            "before and after the refit.")
    with recording("depthstation_explain", target, description=desc) as rec:
        if rec is None:
            return
        sides: list[tuple[str, Any]] = [("before", ex.before)]
        if ex.after is not None:
            sides.append(("after", ex.after))
        for label, loc in sides:
            for fam in ("column", "standpoint", "albedo", "time"):
                for k, t in enumerate(loc.family(fam)):
                    rec.set_time("group", sequence=k)
                    rec.log(f"{fam}/{label}", rr.Scalars(t.diff * 1000))
