"""Do the registration's 95 % bands hold the truth 95 % of the time? (run by hand, not by pytest)

    nice -n 10 .venv/bin/python benchmarks/bench_registration_coverage.py [--walks 20] [--frames 20]
        [--every 2] [--width 256] [--errors 0,0.01,-0.01] [--mode similarity] [--noise-free]
        [--out coverage.csv]

Repeated simulated walks round the room's table (the simulator's clean `d455-ideal` model, no
flying pixels, with a known depth-scale error e through its `depth_scale` effect; not `d455`, whose
unit's own calibration errors a registration rightly absorbs, so that its truth would not be e)
give what RGB-D SLAM would estimate on that depth: the true trajectory scaled by (1 + e) and moved
into its own frame by a random rigid offset (up to 2 deg, 10 cm). `register(mode=...)` fits it
back from the identity; the truth is the inverse of that offset and scale. Per walk and quantity
(the scale, the rotation about each axis, the translation along each axis) the band holds the
truth or not; the table gives the share held, its Wilson 95 % interval, and the estimates' mean
error and spread against the band's mean half width (a bias shows as a mean error; a too narrow
band as spread > half width / 1.96), per truth and pooled over the truths ("all": the band does
not depend on e, and the pooled share is what ~200 walks resolve to +-3 %). Seeds, walk radius
and offsets vary per walk. `--noise-free` drops the matching noise (what is left: quantisation,
dropout) to show what the fit itself adds. Small frames and few frames per walk keep a walk to
seconds of CPU (4-15 s of wall time on the shared 2-core machine, by its load); the CSV is
rewritten after every round, so a run stopped early keeps its walks.
"""

from __future__ import annotations

import argparse
import csv
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.capture.registry import open_inputs
from depthstation.core.geometry import rodrigues
from depthstation.core.lazy_open3d import open3d
from depthstation.evaluate.scan.reference import sample_reference_points
from depthstation.evaluate.scan.registration import _rotvec, register
from depthstation.evaluate.scan.trajectory import compose_similarity, decompose_similarity, read_tum
from depthstation.simulate.model import load_model
from depthstation.simulate.poses import walk_around
from depthstation.simulate.poses import write_tum as write_poses
from depthstation.simulate.scan_sequence import simulate_scan


def one_walk(root: Path, seed: int, error: float, args: argparse.Namespace) -> dict[str, Any]:
    """Simulate, register, and compare one walk with its truth."""
    rng = np.random.default_rng([seed, round(error * 1e6) % 2**31])
    model = load_model("d455-ideal").without_effect("flying_pixels").with_effect("depth_scale",
                                                                           scale_error=error)
    if args.noise_free:
        model = model.without_effect("disparity_noise").without_effect("window_noise")
    d = root / f"walk_{seed}_{error:+.4f}"
    d.mkdir(parents=True)
    n = args.frames
    poses = walk_around(np.array([0.0, -0.75, 0.0]), radius_m=float(rng.uniform(1.7, 2.3)),
                        speed_m_s=2 * np.pi * 2.0 * 30 / n, frames=n, bob_m=0.03)
    write_poses(d / "walk.txt", np.arange(n) / 30.0, poses)
    # the depth's noise drawn afresh for every walk: walks of one seed but another truth sharing it
    # were not independent (a seed's two walks missed together)
    session = simulate_scan("room", d / "walk.txt", model, d / "session", width=args.width,
                            height=args.width * 9 // 16, color=False, seed=int(rng.integers(2**31)))
    truth = read_tum(session / "trajectory.txt")
    axis = rng.normal(size=3)
    turn = rodrigues(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.0, 2.0)))
    offset = compose_similarity(1.0 + error, turn, rng.uniform(-0.1, 0.1, 3))
    slam = truth.transformed(offset)
    o3d = open3d()
    mesh = o3d.io.read_triangle_mesh(str(session / "scene.ply"))
    reg = register(open_inputs([session])[0], slam, mesh, sample_reference_points(mesh), mode=args.mode,
                   every=args.every)
    want = np.linalg.inv(offset)  # slam frame -> reference frame
    s_true, r_true, t_true = decompose_similarity(want)
    s, r, t = decompose_similarity(reg.given_matrix)
    row: dict[str, Any] = {"seed": seed, "error": error, "frames": reg.icp.get("frames"),
                           "scale": s, "scale_true": s_true}
    rot_err = np.degrees(_rotvec(r @ r_true.T))
    tr_err = t - t_true
    for pre, bands in (("", reg.bands()),):
        if bands is None:
            row[f"{pre}band"] = False
            continue
        lo, hi = bands.get("scale_band95", (np.nan, np.nan))
        row.update({f"{pre}band": True, f"{pre}scale_lo": lo, f"{pre}scale_hi": hi,
                    f"{pre}scale_dof": bands.get("dof", {}).get("scale", np.nan)})
        dof = bands.get("dof", {})
        for k, ax in enumerate("xyz"):
            row[f"rot_{ax}_err_deg"] = rot_err[k]
            row[f"{pre}rot_{ax}_u95_deg"] = bands["rotation_u95_deg"][k]
            row[f"t_{ax}_err_m"] = tr_err[k]
            row[f"{pre}t_{ax}_u95_m"] = bands["translation_u95_m"][k]
            if dof:
                row[f"{pre}rot_{ax}_dof"] = dof["rotation"][k]
                row[f"{pre}t_{ax}_dof"] = dof["translation"][k]
        row[f"{pre}blocks"] = bands["blocks"]
    return row


def _share(held: list[bool]) -> str:
    """Share held with a Wilson 95 % interval."""
    n = len(held)
    if n == 0:
        return "-"
    p = sum(held) / n
    z = 1.96
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return f"{100 * p:5.1f} % ({100 * (centre - half):.0f}-{100 * (centre + half):.0f} %, n={n})"


def table(rows: list[dict[str, Any]], pre: str = "") -> list[str]:
    """Per truth and pooled over the truths: the share of walks whose band (`pre`: which band)
    holds the truth, the estimates' mean error and spread, and the band's mean half width."""
    lines = ["| truth e | quantity | band holds the truth | mean error | error spread | mean U95 |",
             "|---|---|---|---|---|---|"]
    errors = sorted({r["error"] for r in rows})
    for e in [*errors, None] if len(errors) > 1 else errors:
        mine = [r for r in rows if (e is None or r["error"] == e) and r.get(f"{pre}band")]
        if not mine:
            continue
        label = "all" if e is None else f"{100 * e:+.0f} %"
        # the scale as the depth-scale error it stands for, in %
        err = np.array([100 * (1 / r["scale"] - 1 / r["scale_true"]) for r in mine])
        u95 = np.array([100 * (1 / r[f"{pre}scale_lo"] - 1 / r[f"{pre}scale_hi"]) / 2 for r in mine])
        held = [r[f"{pre}scale_lo"] <= r["scale_true"] <= r[f"{pre}scale_hi"] for r in mine]
        lines.append(f"| {label} | depth-scale error (%) | {_share(held)} | {err.mean():+.4f} | "
                     f"{err.std(ddof=1):.4f} | {u95.mean():.4f} |")
        for name, unit, scale in (("rot", "deg", 1.0), ("t", "mm", 1e3)):
            for ax in "xyz":
                key = "deg" if name == "rot" else "m"
                e_ = np.array([r[f"{name}_{ax}_err_{key}"] for r in mine]) * scale
                u_ = np.array([r[f"{pre}{name}_{ax}_u95_{key}"] for r in mine]) * scale
                what = f"rotation about {ax} ({unit})" if name == "rot" else f"translation {ax} ({unit})"
                lines.append(f"| {label} | {what} | {_share(list(np.abs(e_) <= u_))} | "
                             f"{e_.mean():+.4f} | {e_.std(ddof=1):.4f} | {u_.mean():.4f} |")
    return lines


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Every walk as a CSV row (replaced whole: written beside, then renamed)."""
    keys = sorted({key for r in rows for key in r})
    tmp = path.with_name(path.name + ".part")
    with tmp.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--walks", type=int, default=20, help="walks per truth")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--every", type=int, default=2, help="register on every n-th frame")
    ap.add_argument("--width", type=int, default=256, help="a 16:9 mode of the D455 (256: 256x144)")
    ap.add_argument("--errors", default="0,0.01,-0.01")
    ap.add_argument("--mode", default="similarity", choices=("similarity", "rigid"))
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--noise-free", action="store_true", help="no matching noise (white or windowed)")
    ap.add_argument("--out", type=Path, default=None, help="CSV of every walk")
    args = ap.parse_args()
    errors = [float(x) for x in args.errors.split(",")]
    if args.mode == "rigid":
        errors = [0.0]
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.walks):
            for e in errors:
                rows.append(one_walk(Path(tmp), args.seed0 + k, e, args))
            print(f"{k + 1}/{args.walks} walks per truth, {time.perf_counter() - t0:.0f} s", flush=True)
            if args.out is not None:  # after every round: a long run stopped early keeps its walks
                write_rows(args.out, rows)
    print(f"{len(rows)} walks ({args.frames} frames of {args.width}x{args.width * 9 // 16}, registered on "
          f"every {args.every}th, --register {args.mode}) in {time.perf_counter() - t0:.0f} s")
    print("\n".join(table(rows)))


if __name__ == "__main__":
    main()
