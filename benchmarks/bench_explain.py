"""Explain on a 20-standpoint simulated session of 30 frames each (target: < 5 minutes on 2 cores)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    from depthstation.protocol import load_protocol
    from simulate.checkerboard import simulate_checkerboard

    proto = load_protocol("checkerboard-d455")
    names = [s.name for s in proto.plan.standpoints()][:20]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        sim = simulate_checkerboard(proto, "d455", Path(tmp) / "real", frames=30, seed=1, standpoints=names)
        t1 = time.perf_counter()
        r = subprocess.run([str(ROOT / ".venv/bin/depthstation"), "explain", str(sim), "--board",
                            str(ROOT / "protocols/checkerboard-d455.toml"), "--model", "d455", "--out",
                            str(Path(tmp) / "out"), "--frames", "30"], capture_output=True, text=True)
        t2 = time.perf_counter()
        print(r.stdout.strip() or r.stderr[-1000:])
        print(f"input simulation: {t1 - t0:.1f} s; explain (20 standpoints x 30 frames): {t2 - t1:.1f} s "
              f"(target 300 s, ratio {(t2 - t1) / 300:.2f})")
        sys.exit(0 if r.returncode == 0 and t2 - t1 < 300 else 1)


if __name__ == "__main__":
    main()
