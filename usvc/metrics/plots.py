"""Plots of a scene's relocalization results: error CDFs (CSV for DVC, PNG) and a trajectory.

The CSVs use one fixed schema (`error`, `fraction`) so DVC's built-in `linear` template can
draw every scene the same way and `dvc plots diff` can overlay experiments. Failed queries are
infinitely wrong (as in the summary), so each CDF tops out at the success rate, not at 1.
In the PNG, translation and rotation each get an x axis fitted to their own errors (`cdf_x_limit`).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # headless: stages run on servers and in CI
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
import numpy as np  # noqa: E402

from usvc.core.errors import UsvcError  # noqa: E402
from usvc.core.pose_errors import (  # noqa: E402
    DEPTH_RELATIVE_THRESHOLDS,
    METRIC_THRESHOLDS,
)

TRANS_CDF, ROT_CDF, PER_QUERY = "trans_cdf.csv", "rot_cdf.csv", "per_query.csv"
CDF_PNG, TRAJECTORY_PNG = "cdf.png", "trajectory.png"
_DPI = 100


def error_cdf(errors: np.ndarray, failed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(sorted errors, fraction of all queries at or below each), starting at (0, 0).

    Failed or non-finite errors are left out of the curve but stay in the denominator.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise UsvcError("error CDF: no queries")
    ok = np.isfinite(e) if failed is None else np.isfinite(e) & ~np.asarray(failed, dtype=bool)
    x = np.sort(e[ok])
    frac = np.arange(1, x.size + 1) / e.size
    return np.concatenate([[0.0], x]), np.concatenate([[0.0], frac])


def write_cdf_csv(path: Path, errors: np.ndarray, failed: np.ndarray | None = None) -> None:
    x, frac = error_cdf(errors, failed)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["error", "fraction"])
        w.writerows((f"{a:.6g}", f"{b:.6g}") for a, b in zip(x, frac))


def write_rows_csv(path: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, (2,3) unit axes of largest spread): a top-down view whatever the scene's up axis."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    mean = p.mean(axis=0)
    if len(p) < 2:
        return mean, np.eye(3)[:2]
    _, _, vt = np.linalg.svd(p - mean, full_matrices=False)
    axes = np.eye(3)[:2] if vt.shape[0] < 2 else vt[:2]
    return mean, axes


# Trajectory styles: ground truth and estimates differ in colour and marker, so the plot reads
# in grey scale too; failed queries are red.
_GT_STYLE = {"marker": "o", "s": 30, "facecolors": "none", "edgecolors": "tab:green", "linewidths": 1.2}
_EST_STYLE = {"marker": "^", "s": 18, "c": "tab:blue"}
_FAILED_STYLE = {"marker": "X", "s": 30, "c": "tab:red"}
_ERROR_LINE = {"color": "0.55", "lw": 0.8}


def trajectory_figure(gt: np.ndarray, est: np.ndarray, failed: np.ndarray, title: str) -> Any:
    """Top-down view of ground-truth vs estimated camera centres, each pair joined by a grey line (paper Fig. 5).

    Framed on the ground truth: a wild estimate would otherwise shrink the trajectory to a dot; the
    legend counts the estimates left outside the frame and the queries with no estimate at all.
    """
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 3)
    est = np.asarray(est, dtype=np.float64).reshape(-1, 3)
    failed = np.asarray(failed, dtype=bool).reshape(-1)
    mean, axes = principal_axes(gt)
    g = (gt - mean) @ axes.T
    e = (est - mean) @ axes.T  # NaN rows (no estimate) stay NaN and are not drawn
    has_est = np.all(np.isfinite(e), axis=1)
    fig, ax = plt.subplots(figsize=(5.5, 5.0), dpi=_DPI)
    if has_est.any():
        ax.add_collection(LineCollection(np.stack([g[has_est], e[has_est]], axis=1), zorder=1,
                                         label="error (ground truth to estimate)", colors=_ERROR_LINE["color"],
                                         linewidths=_ERROR_LINE["lw"]))
    ax.scatter(g[:, 0], g[:, 1], label="ground truth", zorder=2, **_GT_STYLE)
    ok, bad = has_est & ~failed, has_est & failed
    ax.scatter(e[ok, 0], e[ok, 1], label="estimate", zorder=3, **_EST_STYLE)
    if bad.any():
        ax.scatter(e[bad, 0], e[bad, 1], label="estimate (failed)", zorder=3, **_FAILED_STYLE)
    lo, hi = g.min(axis=0), g.max(axis=0)
    pad = 0.25 * max(float((hi - lo).max()), 1e-9)
    (x0, y0), (x1, y1) = lo - pad, hi + pad
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    notes = []
    outside = has_est & ((e[:, 0] < x0) | (e[:, 0] > x1) | (e[:, 1] < y0) | (e[:, 1] > y1))
    if outside.any():
        notes.append(f"{int(outside.sum())} estimate(s) outside the frame")
    if (~has_est).any():
        notes.append(f"{int((~has_est).sum())} quer{'y' if (~has_est).sum() == 1 else 'ies'} without an estimate")
    if notes:
        ax.plot([], [], " ", label="; ".join(notes))  # a text-only legend entry
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("principal axis 1 (scene units)")
    ax.set_ylabel("principal axis 2 (scene units)")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def plot_trajectory(path: Path, gt: np.ndarray, est: np.ndarray, failed: np.ndarray, title: str) -> None:
    fig = trajectory_figure(gt, est, failed, title)
    fig.savefig(path)
    plt.close(fig)


# Accuracy thresholds of the summary (pose_errors), drawn on the CDFs where they fall inside the axis.
METRIC_THRESHOLDS_CM = tuple(sorted({100.0 * m for _, m, _ in METRIC_THRESHOLDS}))
RELATIVE_THRESHOLDS_PCT = tuple(sorted({100.0 * f for _, f, _ in DEPTH_RELATIVE_THRESHOLDS}))  # the acc_rel_* ones
ROTATION_THRESHOLDS_DEG = tuple(sorted({d for _, _, d in (*METRIC_THRESHOLDS, *DEPTH_RELATIVE_THRESHOLDS)}))
# The x axis shows every successful error up to OUTLIER_FACTOR x their 90th percentile (the rest are
# counted in a corner, not drawn), 10 % past the largest, at a round number ...
CDF_PERCENTILE, OUTLIER_FACTOR = 90.0, 3.0
CDF_MIN_SPAN = 1.0  # ... and spans at least this much (1 cm, 1 deg, 1 % of depth): the tightest threshold


def _nice_ceil(x: float) -> float:
    """The smallest 1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k at or above x (x > 0)."""
    exp = 10.0 ** np.floor(np.log10(x))
    for m in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if m * exp >= x * (1 - 1e-12):
            return float(m * exp)
    return float(10.0 * exp)


def cdf_x_limit(errors: np.ndarray, failed: np.ndarray | None = None, min_span: float = CDF_MIN_SPAN) -> float:
    """Right end of a CDF's x axis, from the data: 10 % past the largest successful, finite error that is
    no outlier (at most OUTLIER_FACTOR x the CDF_PERCENTILE), rounded up to a round number, at least
    `min_span` (also when nothing succeeded). Translation and rotation each get their own."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    ok = np.isfinite(e) if failed is None else np.isfinite(e) & ~np.asarray(failed, dtype=bool).reshape(-1)
    if not ok.any():
        return float(min_span)
    e = e[ok]
    inliers = e[e <= OUTLIER_FACTOR * float(np.percentile(e, CDF_PERCENTILE))]
    top = float(inliers.max()) if inliers.size else 0.0
    return float(min_span) if top <= 0.0 else max(float(min_span), _nice_ceil(1.1 * top))


def _cdf_axis(ax: Any, errors: np.ndarray, failed: np.ndarray, label: str, thresholds: Sequence[float]) -> None:
    x, frac = error_cdf(errors, failed)
    upper = cdf_x_limit(errors, failed)
    # the last step runs on to the axis' end, so the plateau (the success rate) stays visible
    ax.step(np.append(x, max(upper, x[-1])), np.append(frac, frac[-1]), where="post", color="tab:blue")
    for thr in thresholds:
        if thr <= upper:
            ax.axvline(thr, color="0.6", ls="--", lw=0.8)
    beyond = int(np.sum(x[1:] > upper))
    if beyond:
        ax.text(0.98, 0.04, f"{beyond} beyond {upper:g}", transform=ax.transAxes, ha="right", fontsize=8, color="0.4")
    ax.set_xlim(0.0, upper)
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel(label)
    ax.set_ylabel("fraction of queries")
    ax.grid(alpha=0.3)


def cdf_figure(trans: np.ndarray, trans_label: str, trans_thresholds: Sequence[float],
               rot: np.ndarray, failed: np.ndarray, title: str) -> Any:
    """Translation and rotation error CDFs side by side, each x axis fitted to its own errors."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(8.0, 3.4), dpi=_DPI)
    _cdf_axis(a, trans, failed, trans_label, trans_thresholds)
    _cdf_axis(b, rot, failed, "rotation error (deg)", ROTATION_THRESHOLDS_DEG)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_cdf(path: Path, trans: np.ndarray, trans_label: str, trans_thresholds: Sequence[float],
             rot: np.ndarray, failed: np.ndarray, title: str) -> None:
    fig = cdf_figure(trans, trans_label, trans_thresholds, rot, failed, title)
    fig.savefig(path)
    plt.close(fig)


def write_plots(out_dir: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str],
                metric_scale: float | None, median_depth: float | None, title: str) -> list[Path]:
    """Write the per-query CSV, both CDF CSVs, cdf.png and trajectory.png into `out_dir`.

    Translation is in cm when the scene is metric, else in % of the median scene depth.
    """
    if not rows:
        raise UsvcError("plots: no queries")
    out_dir = Path(out_dir)
    failed = np.array([r["failed"] for r in rows], dtype=bool)
    rot = np.array([r["rot_deg"] for r in rows], dtype=np.float64)
    trans = np.array([r["trans"] for r in rows], dtype=np.float64)
    if metric_scale is not None:
        trans_x, label, thr = trans * metric_scale * 100.0, "translation error (cm)", METRIC_THRESHOLDS_CM
    elif median_depth is not None:
        trans_x, label, thr = 100.0 * trans / median_depth, "translation error (% of median depth)", \
            RELATIVE_THRESHOLDS_PCT
    else:
        raise UsvcError("plots: translation errors need a metric scale or a median scene depth")
    write_rows_csv(out_dir / PER_QUERY, rows, columns)
    write_cdf_csv(out_dir / TRANS_CDF, trans_x, failed)
    write_cdf_csv(out_dir / ROT_CDF, rot, failed)
    plot_cdf(out_dir / CDF_PNG, trans_x, label, thr, rot, failed, title)
    gt = np.array([[r["gt_x"], r["gt_y"], r["gt_z"]] for r in rows], dtype=np.float64)
    est = np.array([[r["est_x"], r["est_y"], r["est_z"]] for r in rows], dtype=np.float64)
    plot_trajectory(out_dir / TRAJECTORY_PNG, gt, est, failed, title)
    return [out_dir / n for n in (PER_QUERY, TRANS_CDF, ROT_CDF, CDF_PNG, TRAJECTORY_PNG)]
