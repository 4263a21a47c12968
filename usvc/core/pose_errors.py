"""Pose error metrics, following ACE's evaluation rules (the poses file: usvc.core.poses_file).

Rules (see the design notes): translation error is the distance between camera centres,
rotation error is the angle of R_est R_gtᵀ, accuracies use a strict "<" on both errors, and a
median is element ⌊N/2⌋ of the sorted list. A query without a pose counts as infinitely wrong,
so failures lower the accuracies and push the medians up instead of being dropped.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers

# (name, translation threshold in metres, rotation threshold in degrees)
METRIC_THRESHOLDS: tuple[tuple[str, float, float], ...] = (
    ("acc_10cm_5deg", 0.10, 5.0),
    ("acc_5cm_5deg", 0.05, 5.0),
    ("acc_2cm_2deg", 0.02, 2.0),
    ("acc_1cm_1deg", 0.01, 1.0),
)
RELATIVE_THRESHOLD = ("acc_5deg_3pct", 0.03, 5.0)  # fraction of median depth, degrees
# 7-Scenes' thresholds as fractions of the median scene depth (about 1.5 m there; 5 cm / 1.5 m =
# 3.33 %, 2 cm = 1.33 %, 1 cm = 0.667 %), so a scene without metric scale reads like 7-Scenes:
# acc_rel_5cm_5deg is acc_5cm_5deg of the same scene scaled to a 1.5 m median depth.
REFERENCE_MEDIAN_DEPTH_M = 1.5
DEPTH_RELATIVE_THRESHOLDS: tuple[tuple[str, float, float], ...] = (
    ("acc_rel_5cm_5deg", 0.05 / REFERENCE_MEDIAN_DEPTH_M, 5.0),
    ("acc_rel_2cm_2deg", 0.02 / REFERENCE_MEDIAN_DEPTH_M, 2.0),
    ("acc_rel_1cm_1deg", 0.01 / REFERENCE_MEDIAN_DEPTH_M, 1.0),
)


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray | float:
    """Angle of R_est R_gtᵀ in degrees, for single (3,3) or batched (N,3,3) rotations."""
    R_est = np.asarray(R_est, dtype=np.float64)
    R_gt = np.asarray(R_gt, dtype=np.float64)
    if R_est.shape[-2:] != (3, 3) or R_gt.shape[-2:] != (3, 3):
        raise UsvcError(f"rotations must be (..., 3, 3), got {R_est.shape} and {R_gt.shape}")
    # atan2(sin, cos) instead of arccos(cos): arccos loses precision near 0° (a 1e-8 rad
    # error reads as ~1e-6°) and needs clipping when rounding leaves |cos| > 1.
    M = np.einsum("...ij,...kj->...ik", R_est, R_gt)
    cos = (np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin = np.linalg.norm(axis, axis=-1) / 2.0
    angle = np.degrees(np.arctan2(sin, cos))
    return float(angle) if angle.ndim == 0 else angle


def translation_error(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray) -> np.ndarray | float:
    """Distance between estimated and true camera centres, in scene units."""
    d = np.linalg.norm(camera_centers(R_est, t_est) - camera_centers(R_gt, t_gt), axis=-1)
    return float(d) if np.ndim(d) == 0 else d


def _median(values: np.ndarray) -> float:
    """ACE's median: element ⌊N/2⌋ of the sorted list (no averaging for even N)."""
    return float(np.sort(values)[len(values) // 2])


def summarize(
    rot_deg: np.ndarray | Sequence[float],
    trans: np.ndarray | Sequence[float],
    metric_scale: float | None,
    median_depth: float | None,
    failed: np.ndarray | Sequence[bool] | None,
    ms_per_query: float | None = None,
) -> dict[str, float | int | None]:
    """Accuracies and medians over all queries; failures (mask or non-finite errors) are infinitely wrong.

    `trans` is in scene units; `metric_scale` is metres per scene unit (None: no metric figures);
    `median_depth` (scene units) enables the scale-free translation figures.
    """
    rot = np.asarray(rot_deg, dtype=np.float64).reshape(-1)
    tr = np.asarray(trans, dtype=np.float64).reshape(-1)
    if rot.shape != tr.shape:
        raise UsvcError(f"summarize: {rot.size} rotation errors but {tr.size} translation errors")
    n = rot.size
    if n == 0:
        raise UsvcError("summarize: no queries to summarize")
    bad = ~(np.isfinite(rot) & np.isfinite(tr))
    if failed is not None:
        failed_mask = np.asarray(failed, dtype=bool).reshape(-1)
        if failed_mask.shape != rot.shape:
            raise UsvcError(f"summarize: failed mask has {failed_mask.size} entries for {n} queries")
        bad |= failed_mask
    rot = np.where(bad, np.inf, rot)
    tr = np.where(bad, np.inf, tr)
    if metric_scale is not None and not (math.isfinite(metric_scale) and metric_scale > 0):
        raise UsvcError(f"summarize: metric_scale must be positive and finite, got {metric_scale}")
    if median_depth is not None and not (math.isfinite(median_depth) and median_depth > 0):
        raise UsvcError(f"summarize: median_depth must be positive and finite, got {median_depth}")

    out: dict[str, float | int | None] = {}
    for key, max_m, max_deg in METRIC_THRESHOLDS:
        out[key] = None if metric_scale is None else float(np.mean((tr * metric_scale < max_m) & (rot < max_deg)))
    key, frac, max_deg = RELATIVE_THRESHOLD
    out[key] = None if median_depth is None else float(np.mean((tr < frac * median_depth) & (rot < max_deg)))
    for key, frac, max_deg in DEPTH_RELATIVE_THRESHOLDS:
        out[key] = None if median_depth is None else float(np.mean((tr < frac * median_depth) & (rot < max_deg)))
    med_trans = _median(tr)
    out["median_rot_deg"] = _median(rot)
    out["median_trans_cm"] = None if metric_scale is None else med_trans * metric_scale * 100.0
    out["median_trans_rel"] = None if median_depth is None else med_trans / median_depth
    # the median translation in centimetres once the scene is scaled to a 1.5 m median depth
    out["median_trans_rel_cm"] = (None if median_depth is None
                                  else med_trans / median_depth * REFERENCE_MEDIAN_DEPTH_M * 100.0)
    out["median_trans"] = med_trans
    if ms_per_query is not None:
        out["ms_per_query"] = float(ms_per_query)
    out["n_queries"] = int(n)
    out["n_failed"] = int(bad.sum())
    return out
