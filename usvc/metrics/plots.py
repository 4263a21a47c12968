"""Plots of a scene's relocalization results: error CDFs (CSV for DVC, PNG) and a trajectory.

The CSVs use one fixed schema (`error`, `fraction`) so DVC's built-in `linear` template can
draw every scene the same way and `dvc plots diff` can overlay experiments. Failed queries are
infinitely wrong (as in the summary), so each CDF tops out at the success rate, not at 1.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # headless: stages run on servers and in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from usvc.core.errors import UsvcError  # noqa: E402

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


def plot_trajectory(path: Path, gt: np.ndarray, est: np.ndarray, failed: np.ndarray, title: str) -> None:
    """Ground-truth vs estimated camera centres, each pair joined by a grey line (paper Fig. 5)."""
    mean, axes = principal_axes(gt)
    g = (gt - mean) @ axes.T
    e = (est - mean) @ axes.T  # NaN rows (no estimate) stay NaN and are not drawn
    fig, ax = plt.subplots(figsize=(5.5, 5.0), dpi=_DPI)
    for gi, ei in zip(g, e):
        if np.all(np.isfinite(ei)):
            ax.plot([gi[0], ei[0]], [gi[1], ei[1]], color="0.6", lw=0.8, zorder=1)
    ax.scatter(g[:, 0], g[:, 1], s=12, c="tab:green", label="ground truth", zorder=2)
    good = np.all(np.isfinite(e), axis=1)
    ok, bad = good & ~failed, good & failed
    ax.scatter(e[ok, 0], e[ok, 1], s=12, c="tab:blue", label="estimate", zorder=3)
    if bad.any():
        ax.scatter(e[bad, 0], e[bad, 1], s=16, c="tab:red", marker="x", label="estimate (failed)", zorder=3)
    # Frame the ground truth: a wild estimate would otherwise shrink the trajectory to a dot.
    lo, hi = g.min(axis=0), g.max(axis=0)
    pad = 0.25 * max(float((hi - lo).max()), 1e-9)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("principal axis 1 (scene units)")
    ax.set_ylabel("principal axis 2 (scene units)")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _cdf_axis(ax: Any, errors: np.ndarray, failed: np.ndarray, label: str, threshold: float) -> None:
    x, frac = error_cdf(errors, failed)
    ax.step(x, frac, where="post", color="tab:blue")
    ax.axvline(threshold, color="0.6", ls="--", lw=0.8)
    finite = x[1:]
    upper = max(threshold * 2.0, 1.2 * float(np.percentile(finite, 90))) if finite.size else threshold * 2.0
    ax.set_xlim(0.0, upper)
    ax.set_ylim(0.0, 1.0)
    ax.set_xlabel(label)
    ax.set_ylabel("fraction of queries")
    ax.grid(alpha=0.3)


def plot_cdf(path: Path, trans: np.ndarray, trans_label: str, trans_threshold: float,
             rot: np.ndarray, failed: np.ndarray, title: str) -> None:
    fig, (a, b) = plt.subplots(1, 2, figsize=(8.0, 3.4), dpi=_DPI)
    _cdf_axis(a, trans, failed, trans_label, trans_threshold)
    _cdf_axis(b, rot, failed, "rotation error (deg)", 5.0)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
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
        trans_x, label, thr = trans * metric_scale * 100.0, "translation error (cm)", 5.0
    elif median_depth is not None:
        trans_x, label, thr = 100.0 * trans / median_depth, "translation error (% of median depth)", 3.0
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
