"""Explain on a 20-standpoint simulated session of 30 frames each (target: < 5 minutes on 2 cores),
with discovery on (the library of generic terms searched on every table).

The session has no hidden effect (the same model on both sides), so it is also the full-size null
case: nothing may be selected or discovered and no region may differ, before or after.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    from depthstation.core.protocol import load_protocol
    from depthstation.simulate.checkerboard_session import simulate_checkerboard

    proto = load_protocol("checkerboard-d455")
    names = [s.name for s in proto.plan.standpoints()][:20]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        sim = simulate_checkerboard(proto, "d455", Path(tmp) / "real", frames=30, seed=1, standpoints=names)
        t1 = time.perf_counter()

        def explain(out: str, *extra: str) -> tuple[subprocess.CompletedProcess[str], float, float]:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            start = time.perf_counter()
            r = subprocess.run([str(ROOT / ".venv/bin/depthstation"), "explain", str(sim), "--board",
                                str(ROOT / "protocols/checkerboard-d455.toml"), "--model", "d455", "--out",
                                str(Path(tmp) / out), "--frames", "30", *extra],
                               capture_output=True, text=True)
            wall = time.perf_counter() - start
            used = resource.getrusage(resource.RUSAGE_CHILDREN)
            return r, wall, used.ru_utime + used.ru_stime - before.ru_utime - before.ru_stime

        # the same run without discovery first: the cost of discovery as a same-run ratio
        r0, wall0, cpu0 = explain("out-plain", "--no-discover")
        r, wall, cpu = explain("out")
        print(r.stdout.strip() or r.stderr[-1000:])
        print(f"input simulation: {t1 - t0:.1f} s; explain (20 standpoints x 30 frames) with discovery: "
              f"{wall:.1f} s wall, {cpu:.1f} s CPU (target 300 s wall, ratio {wall / 300:.2f}); without: "
              f"{wall0:.1f} s wall, {cpu0:.1f} s CPU (discovery costs x{cpu / max(cpu0, 1e-9):.2f} in CPU)"
              + ("" if r0.returncode == 0 else " [--no-discover run failed]"))
        t2 = t1 + wall
        clean = False
        if r.returncode == 0:
            data = json.loads((Path(tmp) / "out" / "explain.json").read_text())
            after = data.get("mismatch_after") or {"significant": False, "regions": []}
            searched = data["discovery"]["library_size"]
            print(f"null case: selected {data['selected'] or 'nothing'}; discovered "
                  f"{[d['axes'] for d in data['discovered']] or 'nothing'} ({searched} generic terms "
                  f"searched); regions before "
                  f"{[x['label'] for x in data['mismatch']['regions']]}, after "
                  f"{[x['label'] for x in after['regions']]}")
            clean = (not data["missing_physics"] and not data["discovered"]
                     and not data["mismatch"]["significant"])
        sys.exit(0 if r.returncode == 0 and t2 - t1 < 300 and clean else 1)


if __name__ == "__main__":
    main()
