"""Explain's false-alarm rates on the null case, over many sessions: how often a session simulated
with the model itself is called different (a significant mismatch) or given a discovered term.

Why: the tests run one seed per case, which says nothing about a rate. Each session here is
`tests/test_explain_discover.py::test_null_discovers_nothing`'s (320x180, 6 frames, 1-3 m, 0 and
30 deg, the plain D455 model), simulated with its own seed and explained with re-simulation; about
10 s each on 2 cores. Nominal: 5 % for a mismatch (Holm over all tests of a run).

Run by hand:
    .venv/bin/python benchmarks/explain_null_rate.py --seeds 20-77
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def seed_range(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="20-39", help="session seeds, e.g. 20-77")
    ap.add_argument("--explain-seed", type=int, default=3)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from explain_cases import conceal, wide_protocol

    from depthstation.evaluate.explain.run import run_explain
    from depthstation.simulate.checkerboard_session import simulate_checkerboard
    from depthstation.simulate.model import load_model

    proto = wide_protocol(320, 180)
    proto = replace(proto, plan=replace(proto.plan, start_distance_m=1.0, step_m=0.5, max_distance_m=3.0))
    seeds = seed_range(args.seeds)
    mismatch, discovered, left_out = [], [], []
    t0 = time.perf_counter()
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            sim = simulate_checkerboard(proto, "d455", Path(tmp) / "sim", frames=6, seed=seed)
            real = conceal(sim, Path(tmp) / "real", None)
            data = run_explain([real], ROOT / "protocols" / "demo-d455.toml", load_model("d455"),
                               Path(tmp) / "out", frames=6, seed=args.explain_seed)
        if data["mismatch"]["significant"]:
            mismatch.append(seed)
        if data["discovered"]:
            discovered.append((seed, [d["expression"] for d in data["discovered"]]))
        if any(data["standpoints_left_out"].values()):
            left_out.append(seed)
        print(f"seed {seed}: mismatch {data['mismatch']['significant']}, "
              f"discovered {[d['quantity'] + ' along ' + '/'.join(d['axes']) for d in data['discovered']]}, "
              f"left out {json.dumps({k: v for k, v in data['standpoints_left_out'].items() if v})}",
              flush=True)
    n = len(seeds)
    print(f"{n} null sessions in {time.perf_counter() - t0:.0f} s: significant mismatch in {len(mismatch)} "
          f"({len(mismatch) / n:.1%}) {mismatch}; a discovered term in {len(discovered)} "
          f"({len(discovered) / n:.1%}) {discovered}; a standpoint one side lacked in {len(left_out)}")


if __name__ == "__main__":
    main()
