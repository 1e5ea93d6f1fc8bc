"""The explain result in rerun: the summary text, the real-minus-sim residual grid before and after
the refit as distance x inclination heatmaps, and the residual along each hidden axis."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from depthstation.core.rerun_bridge import RerunTarget, recording, send_heatmap, send_text
from depthstation.evaluate.explain.locate import residual_grid

if TYPE_CHECKING:
    from depthstation.evaluate.explain.run import Explanation


def log_explanation(ex: Explanation, target: RerunTarget) -> None:
    import rerun as rr

    sel = ", ".join(c.effect for c in ex.attribution.selected) or "nothing"
    found = ", ".join(f"{t.quantity} along {'/'.join(t.axes)} ({t.effect})"
                      for t in (ex.discovery.terms if ex.discovery is not None else [])) or "nothing"
    desc = (f"# depthstation explain\nSelected: {sel}.\nDiscovered outside the catalogue: {found}.\n"
            "`residual/bias/<before|after>`: mean z error "
            "real - sim (mm) per distance x inclination cell; `residual/noise/...`: temporal variance "
            "real - sim (mm^2); series: the same along columns, standpoints, albedo and time.")
    with recording("depthstation_explain", target, description=desc) as rec:
        if rec is None:
            return
        send_text(rec, "summary", desc)
        sides: list[tuple[str, Any]] = [("before", ex.before)]
        if ex.after is not None:
            sides.append(("after", ex.after))
        for label, loc in sides:
            for kind, scale, unit in (("bias", 1e3, "mm"), ("noise", 1e6, "mm^2")):
                grid = residual_grid(loc, kind)
                if grid is not None:
                    de, ie, m = grid
                    send_heatmap(rec, f"residual/{kind}/{label}", m * scale, de, ie,
                                 quantity=f"real - sim ({kind}), {label} the refit", unit=unit)
            for fam in ("column", "standpoint", "albedo", "time"):
                # one position per group label over both sides: a group one side lacks moves no other
                groups = list(dict.fromkeys(t.label for _, lc in sides for t in lc.family(fam)))
                for t in loc.family(fam):
                    rec.set_time("group", sequence=groups.index(t.label))
                    rec.log(f"{fam}/{label}", rr.Scalars(t.diff * 1000))
