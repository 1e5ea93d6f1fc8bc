"""Chaotic guided sessions through the device double: `--sessions N` seeds, each a session with
faults drawn at random (tests/chaos_live.py), and the figures: how many ended complete at once,
how many stopped with a one-line reason and completed on --resume, how many broke a rule (an
internal error, a failed resume, a lost standpoint, numbers that do not add up), which faults hit,
and the time per session.

    .venv/bin/python benchmarks/chaos_sessions.py --sessions 200
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from chaos_live import run_session


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--first-seed", type=int, default=0)
    args = ap.parse_args()
    outcomes = []
    t0 = time.monotonic()
    for seed in range(args.first_seed, args.first_seed + args.sessions):
        with tempfile.TemporaryDirectory() as d:
            o = run_session(seed, Path(d))
        outcomes.append(o)
        mark = "BROKEN" if o.problems else "resumed" if o.resumed else "complete"
        print(f"seed {seed:4d} {mark:8s} {o.seconds:5.1f} s  hit {o.faults_hit}  {o.chaos}"
              + (f"  | {o.reason}" if o.reason else "") + (f"  | {o.problems}" if o.problems else ""),
              flush=True)
    n = len(outcomes)
    broken = [o for o in outcomes if o.problems]
    resumed = [o for o in outcomes if o.resumed and not o.problems]
    reasons = collections.Counter(re.sub(r"/\S+", "PATH", o.reason or "")[:110] for o in resumed)
    secs = sorted(o.seconds for o in outcomes)
    print()
    wall = time.monotonic() - t0
    print(f"{n} sessions in {wall:.0f} s ({secs[n // 2]:.1f} s median, {secs[-1]:.1f} s max)")
    print(f"complete at once: {n - len(resumed) - len(broken)}; stopped with one line and completed on "
          f"--resume: {len(resumed)}; broke a rule: {len(broken)}")
    drawn, hit = sum(o.faults_drawn for o in outcomes), sum(o.faults_hit for o in outcomes)
    fetches = sum(o.fetches for o in outcomes)
    print(f"stalls, unplugs, drops, slow frames drawn: {drawn}, hit: {hit} (over {fetches} frame fetches; "
          "one drawn past a session's last fetch does not hit)")
    failed = sum(o.verdicts_failed for o in outcomes)
    created = sum(o.creation_errors for o in outcomes)
    print(f"self-calibrations failed: {failed}; device creations that threw while re-enumerating: {created}; "
          f"full disks: {sum('disk_full' in o.chaos for o in outcomes)}")
    for why, count in reasons.most_common():
        print(f"  stopped x{count}: {why}")
    for o in broken:
        print(f"  BROKEN seed {o.seed}: {o.chaos}: {o.problems}")
    return 1 if broken else 0


if __name__ == "__main__":
    raise SystemExit(main())
