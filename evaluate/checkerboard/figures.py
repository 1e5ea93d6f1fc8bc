"""The paper's figures for the checkerboard study (Fig. 1, 4, 5, 6, 7) as PNG, units on every axis."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.board import Board
from depthstation.core.forked import run_split
from depthstation.core.heatmaps import POSITIVE, SIGNED, colormap, robust_limits
from depthstation.evaluate.checkerboard.study import StandpointResult


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    """Lay out (tight, unless the figure has its own layout engine), write (120 dpi) and release a
    figure; its path."""
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path


def _save_labelled(fig: Any, path: Path, labels: list[tuple[Any, np.ndarray, np.ndarray, list[str], float]]
                   ) -> Path:
    """`_save` for a figure with labelled markers: laid out first, then the labels placed where the
    axes end up (`place_labels`), measured at the dpi the figure is saved with."""
    fig.set_dpi(120)
    fig.tight_layout()
    for ax, xs, ys, texts, marker_pt in labels:
        place_labels(fig, ax, xs, ys, texts, marker_pt)
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path


def preload_plotting() -> None:
    """Import matplotlib (with the Agg backend) ahead of the figures, e.g. from a thread."""
    _plt()


def fig1_poses(path: Path, results: list[StandpointResult], board: Board, caption: str = "") -> Path:
    """Averaged colour-camera poses around the board (axes x, y, z in red, green, blue; 20 cm)."""
    plt = _plt()
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    poses = [(r.name, r.camera_in_board) for r in results if r.camera_in_board is not None]
    turn = board_turn(np.array([m[:3, 3] for _, m in poses]).reshape(-1, 3))
    pts = board.corner_points() @ turn.T
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c="grey", s=6, label="board corners")
    all_pts = [pts]
    for name, m in poses:
        c = turn @ m[:3, 3]
        for i, col in enumerate(("r", "g", "b")):
            e = c + 0.2 * (turn @ m[:3, i])
            ax.plot([c[0], e[0]], [c[1], e[1]], [c[2], e[2]], color=col, lw=1.5)
        ax.text(c[0], c[1], c[2], f" {name}", fontsize=7)
        all_pts.append(c[None, :])
    p = np.concatenate(all_pts)
    mid, span = (p.max(0) + p.min(0)) / 2, float(np.max(p.max(0) - p.min(0))) / 2 + 0.2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[1] - span, mid[1] + span)
    ax.set_zlim(mid[2] - span, mid[2] + span)
    flipped = turn[2, 2] < 0
    ax.set_xlabel("board x (m)")
    ax.set_ylabel("board -y (m)" if flipped else "board y (m)")
    ax.set_zlabel("board -z (m), towards the cameras" if flipped else "board z (m), towards the cameras")
    ax.set_title("Fig. 1: averaged camera poses in the board frame, cameras above the board (+z; axis "
                 "length 20 cm)" + (f"\n{caption}" if caption else ""), fontsize=10)
    return _save(fig, path)


def board_turn(cameras: np.ndarray) -> np.ndarray:
    """The rotation that puts the cameras on the board's +z side: identity, or half a turn about x
    (x, -y, -z) where the board frame's z points away from the cameras (a chessboard's pose from
    OpenCV, whose z goes into the board, against a ChArUco board's), so that Fig. 1 reads the same
    for both kinds of board."""
    z = cameras[:, 2] if cameras.size else np.zeros(0)
    return np.diag([1.0, -1.0, -1.0]) if z.size and float(np.median(z)) < 0 else np.eye(3)


def place_labels(fig: Any, ax: Any, xs: np.ndarray, ys: np.ndarray, texts: list[str],
                 marker_pt: float, fontsize: float = 7) -> list[Any]:
    """Value labels beside scatter markers that overlap neither each other nor a marker and stay
    inside the axes: for each point (left to right) the first free spot of eight directions at
    growing distance, else the spot that overlaps least; a label away from its marker gets a line
    to it."""
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    to_px = fig.dpi / 72.0
    centres = ax.transData.transform(np.column_stack([xs, ys]))
    r_px = 0.5 * marker_pt * to_px + 1.0
    markers = [(cx - r_px, cy - r_px, cx + r_px, cy + r_px) if np.isfinite([cx, cy]).all() else (0, 0, 0, 0)
               for cx, cy in centres]
    placed: list[tuple[float, float, float, float]] = []
    labels: list[Any] = [None] * len(texts)
    directions = ((1, 1), (-1, 1), (1, -1), (-1, -1), (0, 1.2), (0, -1.2), (1.3, 0), (-1.3, 0))

    def overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> float:
        w = min(a[2], b[2]) - max(a[0], b[0])
        h = min(a[3], b[3]) - max(a[1], b[1])
        return max(w, 0.0) * max(h, 0.0)

    rings = [0.5 * marker_pt + d for d in (1.0, 8.0, 18.0, 30.0)]
    for k in np.argsort(xs, kind="stable"):
        if not (np.isfinite(xs[k]) and np.isfinite(ys[k]) and np.isfinite(centres[k]).all()):
            continue  # not drawn (no value, or none on a log axis)
        best: tuple[float, Any, tuple[float, float, float, float], float] | None = None
        for dist in rings:
            for dx, dy in directions:
                ann = ax.annotate(texts[k], (xs[k], ys[k]), xytext=(dx * dist, dy * dist),
                                  textcoords="offset points", fontsize=fontsize,
                                  ha="left" if dx > 0 else "right" if dx < 0 else "center",
                                  va="bottom" if dy > 0 else "top" if dy < 0 else "center")
                e = ann.get_window_extent(renderer)
                box = (e.x0 - 2, e.y0 - 2, e.x1 + 2, e.y1 + 2)
                outside = (max(frame.x0 - box[0], 0) + max(box[2] - frame.x1, 0)
                           + max(frame.y0 - box[1], 0) + max(box[3] - frame.y1, 0)) * 100
                cost = outside + sum(overlap(box, o) for o in placed) + sum(
                    overlap(box, m) for j, m in enumerate(markers) if j != k) + 0.01 * dist
                if best is None or cost < best[0]:
                    if best is not None:
                        best[1].remove()
                    best = (cost, ann, box, dist)
                else:
                    ann.remove()
                if cost < 1.0:
                    break
            if best is not None and best[0] < 1.0:
                break
        assert best is not None
        cost, ann, box, dist = best
        if dist > rings[0]:  # away from its point (or nowhere free): tied to it by a line
            ann.remove()
            ann = ax.annotate(texts[k], (xs[k], ys[k]), xytext=ann.xyann, textcoords="offset points",
                              fontsize=fontsize, ha=ann.get_ha(), va=ann.get_va(),
                              arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4", "shrinkA": 0,
                                          "shrinkB": 0.5 * marker_pt})
        placed.append(box)
        labels[k] = ann
    return labels


def _usable(results: list[StandpointResult]) -> list[StandpointResult]:
    return [r for r in results if r.usable]


def fig4_reference_std(path: Path, results: list[StandpointResult], caption: str = "") -> Path:
    """Spread of the per-frame reference distances, and the reference pose's own tilt uncertainty.

    Left: std of the per-frame reference distances (the paper's Fig. 4). Right: the inclination's
    uncertainty from random corner noise: per frame (predicted Cramer-Rao x sqrt(frames) against
    the measured std over frames) and of the averaged pose. Static corner bias is not in it.
    """
    plt = _plt()
    rs = _usable(results)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 5))
    d = np.array([r.figures["distance_m"] for r in rs])
    inc = np.array([r.figures["inclination_deg"] for r in rs])
    std = np.array([r.figures.get("reference_distance_std_m", np.nan) for r in rs]) * 1000
    sc = ax.scatter(d, std, c=inc, cmap="viridis", s=40, vmin=0, vmax=90)
    names = [r.name for r in rs]
    fig.colorbar(sc, ax=ax, label="inclination (deg)")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("std of reference distance over frames (mm)")
    ax.set_title("reference-distance spread per standpoint")
    ax.grid(alpha=0.3)
    n = np.array([max(r.frames_used, 1) for r in rs], dtype=np.float64)
    mean_pose = np.array([r.figures.get("inclination_std_deg", np.nan) for r in rs])
    one_frame = mean_pose * np.sqrt(n)
    measured = np.array([r.figures.get("inclination_frame_std_deg", np.nan) for r in rs])
    kw = {"c": inc, "cmap": "viridis", "vmin": 0, "vmax": 90, "edgecolors": "k"}
    sc2 = ax2.scatter(d, one_frame, marker="o", s=50, label="1 frame, predicted (corner noise)", **kw)
    ax2.scatter(d, measured, marker="x", s=50, label="1 frame, measured (std over frames)",
                **{k: v for k, v in kw.items() if k != "edgecolors"})
    ax2.scatter(d, mean_pose, marker="s", s=30, label="averaged pose, predicted", **kw)
    fig.colorbar(sc2, ax=ax2, label="inclination (deg)")
    if np.any(np.isfinite(one_frame) & (one_frame > 0)) or np.any(np.isfinite(measured) & (measured > 0)):
        ax2.set_yscale("log")
    ax2.set_xlabel("distance (m)")
    ax2.set_ylabel("std of the pose inclination (deg)")
    ax2.set_title("reference pose tilt from random corner noise (no static bias)")
    ax2.legend(fontsize=7)
    ax2.grid(alpha=0.3, which="both")
    fig.suptitle("Fig. 4: uncertainty of the reference pose per standpoint"
                 + (f" ({caption})" if caption else ""))
    return _save_labelled(fig, path, [(ax, d, std, names, float(np.sqrt(40))),
                                      (ax2, d, one_frame, names, float(np.sqrt(50)))])


def fig5_pixels(path: Path, r: StandpointResult, caption: str = "") -> Path | None:
    """Per-pixel noise (to the frame's plane) and accuracy (to the reference plane) of one frame."""
    if r.example is None:
        return None
    plt = _plt()
    ex = r.example
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), layout="constrained")  # equal aspect: tight cut labels
    h, w = ex.noise_map_m.shape
    extent = (ex.u0 - 0.5, ex.u0 + w - 0.5, ex.v0 + h - 0.5, ex.v0 - 0.5)
    for ax, img, title in ((axes[0], ex.noise_map_m, "noise: distance to fitted plane"),
                           (axes[1], ex.accuracy_map_m, "accuracy: distance to reference plane")):
        mm = img * 1000
        lo, hi = robust_limits(mm, 99.0, symmetric=True)
        im = ax.imshow(np.ma.masked_invalid(mm), cmap=colormap(SIGNED), vmin=lo, vmax=hi, extent=extent)
        fig.colorbar(im, ax=ax, label="signed orthogonal distance (mm), + = behind")
        ax.set_xlabel("depth pixel u (px)")
        ax.set_ylabel("depth pixel v (px)")
        ax.set_title(title)
    f = r.figures
    fig.suptitle(f"Fig. 5: {r.name}, frame {ex.index} ({f['distance_m']:.2f} m, "
                 f"{f['inclination_deg']:.1f} deg)" + (f"; {caption}" if caption else ""))
    return _save(fig, path)


def fig_over_grid(path: Path, results: list[StandpointResult], key: str, label: str,
                  number: int, caption: str = "") -> Path:
    """Mean (with U95) and std over frames of one figure, per standpoint, over distance x inclination."""
    plt = _plt()
    rs = _usable(results)
    d = np.array([r.figures["distance_m"] for r in rs])
    inc = np.array([r.figures["inclination_deg"] for r in rs])
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    texts: list[tuple[Any, list[str]]] = []
    for ax, suffix, what in ((axes[0], "_m", "mean"), (axes[1], "_std_m", "std over frames")):
        vals = np.array([r.figures.get(key + suffix, np.nan) for r in rs]) * 1000
        u95 = np.array([r.figures.get(key + "_m_u95", np.nan) for r in rs]) * 1000
        signed = key.startswith("accuracy") and what == "mean"
        lo, hi = robust_limits(vals, 98.0, symmetric=signed)
        if not signed:
            lo = min(lo, 0.0)
        sc = ax.scatter(d, inc, c=vals, cmap=colormap(SIGNED if signed else POSITIVE), s=120,
                        edgecolors="k", vmin=lo, vmax=hi)
        fig.colorbar(sc, ax=ax, label=f"{label} {what} (mm)" + (" ± U95" if what == "mean" else ""),
                     extend="both" if signed else "max")
        ax.set_xlabel("distance (m)")
        ax.set_ylabel("inclination (deg)")
        ax.set_ylim(-3, 93)
        ax.grid(alpha=0.3)
        ax.set_title(f"{label}: {what}")
        texts.append((ax, [f"{v:.2f}" + (f" ± {u:.2f}" if what == "mean" and np.isfinite(u) else "")
                           for v, u in zip(vals, u95, strict=True)]))
    fig.suptitle(f"Fig. {number}: {label} per standpoint over distance x inclination"
                 + (f" ({caption})" if caption else ""))
    return _save_labelled(fig, path, [(ax, d, inc, labels, float(np.sqrt(120))) for ax, labels in texts])


def fig_colours(path: Path, results: list[StandpointResult], caption: str = "") -> Path:
    """Black versus white squares: noise and accuracy with their std over frames."""
    plt = _plt()
    rs = _usable(results)
    x = np.arange(len(rs))
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, key in ((axes[0], "noise"), (axes[1], "accuracy")):
        for off, colour, c in ((-0.15, "black", "k"), (0.15, "white", "0.6")):
            m = np.array([r.figures.get(f"{key}_{colour}_m", np.nan) for r in rs]) * 1000
            s = np.array([r.figures.get(f"{key}_{colour}_std_m", np.nan) for r in rs]) * 1000
            ax.errorbar(x + off, m, yerr=s, fmt="o", color=c, label=f"{colour} squares", capsize=3)
        ax.set_xticks(x, [r.name for r in rs], rotation=60, fontsize=7)
        ax.set_ylabel(f"{key} (mm), mean ± std over frames")
        ax.set_xlabel("standpoint")
        ax.set_title(f"{key}: black against white squares per standpoint")
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle("Black vs white squares (p-values in standpoints.csv)"
                 + (f"; {caption}" if caption else ""))
    return _save(fig, path)


def fig_dqt(path: Path, results: list[StandpointResult], caption: str = "") -> Path | None:
    """Intel's Depth Quality Tool metrics per standpoint over distance, with Intel's expected RMS."""
    rs = [r for r in _usable(results) if np.isfinite(r.figures.get("dqt_distance_mm", np.nan))]
    if not rs:
        return None
    plt = _plt()
    d = np.array([r.figures["distance_m"] for r in rs])
    inc = np.array([r.figures["inclination_deg"] for r in rs])

    def col(key: str) -> np.ndarray:
        return np.array([r.figures.get(key, np.nan) for r in rs], dtype=np.float64)

    roi = np.isfinite(col("dqt_roi_distance_mm")).any()
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    kw = {"c": inc, "cmap": "viridis", "vmin": 0, "vmax": 90, "edgecolors": "k", "s": 50}
    ax = axes[0, 0]
    sc = ax.scatter(d, col("dqt_plane_fit_rms_mm"), label="plane-fit RMS, board mask", **kw)
    if roi:
        ax.scatter(d, col("dqt_roi_plane_fit_rms_mm"), marker="s", label="plane-fit RMS, centred ROI", **kw)
    expected = col("dqt_expected_rms_mm")
    per_z2 = expected / (col("dqt_distance_mm") / 1000.0) ** 2
    k = float(np.nanmedian(per_z2)) if np.isfinite(per_z2).any() else np.nan
    if np.isfinite(k):
        zz = np.linspace(0.0, max(float(d.max()) * 1.1, 0.5), 100)
        ax.plot(zz, k * zz**2, "k--", label="Intel expected: Z² · 0.08 px / (f B)")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("plane-fit RMS (mm)")
    ax.set_title("(a) plane-fit RMS against Intel's expected RMS")
    ax.legend(fontsize=7)
    fig.colorbar(sc, ax=ax, label="inclination (deg)")
    ax = axes[0, 1]
    ax.scatter(d, col("dqt_subpixel_rms_px"), label="subpixel RMS (along the rays)", **kw)
    ax.scatter(d, col("dqt_subpixel_rms_tool_px"), marker="x", c="0.4", label="as the DQT's code computes it")
    ax.axhline(0.08, color="k", ls="--", lw=1, label="Intel's 0.08 px")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("subpixel RMS (px)")
    ax.set_title("(b) subpixel RMS")
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    ax.scatter(d, col("dqt_z_accuracy_pct"), label="board mask", **kw)
    if roi:
        ax.scatter(d, col("dqt_roi_z_accuracy_pct"), marker="s", label="centred ROI", **kw)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("Z accuracy (% of ground truth), + = too far")
    ax.set_title("(c) Z accuracy (median, the DQT's sign)")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.scatter(d, col("dqt_fill_rate_pct"), label="fill rate (%)", **kw)
    ax2 = ax.twinx()
    ax2.scatter(d, col("dqt_temporal_noise_pct"), marker="^", c="tab:red", label="temporal noise (%)")
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("fill rate (%)")
    ax2.set_ylabel("temporal noise (% of depth)", color="tab:red")
    ax.set_title("(d) fill rate and temporal noise, board mask")
    for a in axes.ravel():
        a.grid(alpha=0.3)
    fig.suptitle("Intel Depth Quality Tool metrics per standpoint (dqt_* columns of standpoints.csv)"
                 + (f"\n{caption}" if caption else ""))
    return _save(fig, path)


def write_figures(out: Path, results: list[StandpointResult], board: Board,
                  caption: str = "") -> list[Path]:
    """All figures of the study; those without data (no usable standpoint) are left out.
    `caption` (stream resolution, frames) goes into every title. The figures are drawn in two
    processes where the platform forks (`core.forked`: ~3.5 s of matplotlib on one core before)."""
    if not _usable(results):
        return []
    best = min(_usable(results), key=lambda r: abs(r.figures["distance_m"] - 1.7)
               + abs(r.figures["inclination_deg"] - 42.5) / 50)
    jobs: list[tuple[float, Callable[[], Path | None]]] = [  # (seconds each took, serially, job)
        (0.18, partial(fig1_poses, out / "fig1_poses.png", results, board, caption)),
        (0.44, partial(fig4_reference_std, out / "fig4_reference_distance_std.png", results, caption)),
        (0.45, partial(fig5_pixels, out / "fig5_pixels.png", best, caption)),
        (0.43, partial(fig_over_grid, out / "fig6_noise.png", results, "noise", "noise", 6, caption)),
        (0.30, partial(fig_over_grid, out / "fig7_accuracy.png", results, "accuracy", "accuracy", 7,
                       caption)),
        (0.19, partial(fig_colours, out / "fig_black_white.png", results, caption)),
        (0.54, partial(fig_dqt, out / "fig_dqt.png", results, caption)),
    ]
    drawn = run_split([job for _, job in jobs], [cost for cost, _ in jobs])
    return [p for p in drawn if p is not None]
