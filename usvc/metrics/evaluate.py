"""Score estimated query poses against a scene's ground truth, per query and in summary.

The summary follows `pose_errors.summarize` (ACE's rules); the per-query rows keep what the
summary throws away (which query failed, how far off each one was, where its camera is) so
plots and failure analysis need no second pass over the inputs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers
from usvc.core.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.core.scene import Scene
from usvc.relocalize.queries_file import (
    QueryStats,
    RefinementRecords,
    refinement_summary,
)

PER_QUERY_COLUMNS: tuple[str, ...] = (
    "name", "rot_deg", "trans", "trans_cm", "failed", "inliers",
    "gt_x", "gt_y", "gt_z", "est_x", "est_y", "est_z",
)


def check_query_names(kind: str, names: Any, queries: set[str], scene: str) -> None:
    """Refuse poses (or statistics) of images that are not the scene's test queries, naming the first."""
    unknown = sorted(set(names) - queries)
    if unknown:
        more = f" (and {len(unknown) - 1} more)" if len(unknown) > 1 else ""
        raise UsvcError(f"{kind} has a pose for {unknown[0]!r}{more}, which is not a test query of scene {scene!r}")


def evaluate_poses(
    scene: Scene,
    estimates: Mapping[str, tuple[np.ndarray, np.ndarray]],
    query_stats: Mapping[str, QueryStats],
    median_depth: float | None,
) -> tuple[dict[str, float | int | None], list[dict[str, Any]]]:
    """(summary, per-query rows) for the scene's test split.

    A query is failed when it has no estimate or its stats say the solver did not succeed;
    `summarize` then counts it as infinitely wrong. Its row still carries the real errors of
    any pose it got, so a near-miss is visible. ms_per_query is the mean of every reported
    query's time, failures included, since a user waits for those too.
    """
    queries = scene.split("test")
    if not scene.has_poses:
        raise UsvcError(f"scene {scene.name!r} has no ground-truth poses to evaluate against")
    names = {f.name for f in queries}
    check_query_names("poses file", estimates, names, scene.name)
    check_query_names("query statistics", query_stats, names, scene.name)
    if not query_stats:
        raise UsvcError(f"no query statistics for scene {scene.name!r}: cannot report time per query")

    R_gt = np.stack([f.R for f in queries])
    t_gt = np.stack([f.t for f in queries])
    R_est = np.stack([estimates[f.name][0] if f.name in estimates else np.eye(3) for f in queries])
    t_est = np.stack([estimates[f.name][1] if f.name in estimates else np.zeros(3) for f in queries])
    has_est = np.array([f.name in estimates for f in queries])
    rot = np.where(has_est, rotation_error_deg(R_est, R_gt), np.nan)
    trans = np.where(has_est, translation_error(R_est, t_est, R_gt, t_gt), np.nan)
    stats = [query_stats.get(f.name) for f in queries]
    failed = ~has_est | np.array([s is not None and not s.success for s in stats])

    times = [s.seconds for s in query_stats.values()]
    summary = summarize(rot, trans, scene.metric_scale, median_depth, failed,
                        ms_per_query=None if None in times else 1000.0 * float(np.mean(times)))
    summary["median_depth"] = median_depth
    summary["mean_inliers"] = float(np.mean([0 if s is None else s.inliers for s in stats]))

    gt_c = camera_centers(R_gt, t_gt)
    est_c = np.where(has_est[:, None], camera_centers(R_est, t_est), np.nan)
    scale = scene.metric_scale
    rows = [
        {"name": f.name, "rot_deg": float(rot[i]), "trans": float(trans[i]),
         "trans_cm": float(trans[i]) * scale * 100.0 if scale is not None else math.nan,
         "failed": bool(failed[i]), "inliers": 0 if stats[i] is None else stats[i].inliers,
         **{f"gt_{a}": float(gt_c[i, k]) for k, a in enumerate("xyz")},
         **{f"est_{a}": float(est_c[i, k]) for k, a in enumerate("xyz")}}
        for i, f in enumerate(queries)
    ]
    return summary, rows


# The few figures `dvc metrics show` / `dvc exp show` print by default: accuracy at the three
# 7-Scenes thresholds, the median errors and the failures, in results/<scene>/headline.json beside
# metrics.json (all figures). dvc.yaml lists only this file under `metrics:`. A scene without metric
# scale reports the same figures scaled to a 1.5 m median depth (acc_rel_*, median_trans_rel_cm).
HEADLINE_FILE = "headline.json"
HEADLINE_KEYS_METRIC: tuple[str, ...] = ("acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "median_trans_cm",
                                         "median_rot_deg", "n_failed", "n_queries")
HEADLINE_KEYS_RELATIVE: tuple[str, ...] = ("acc_rel_5cm_5deg", "acc_rel_2cm_2deg", "acc_rel_1cm_1deg",
                                           "median_trans_rel_cm", "median_rot_deg", "n_failed", "n_queries")


def headline_figures(summary: Mapping[str, Any], metric: bool) -> dict[str, float | int | None]:
    """The headline subset of an `evaluate_poses` summary: metric figures for a metric scene, else relative ones.

    Every key is present (None where the summary has no value), so every run of a scene has the same columns.
    """
    return {k: summary.get(k) for k in (HEADLINE_KEYS_METRIC if metric else HEADLINE_KEYS_RELATIVE)}


def _is_headline(key: str, value: object) -> bool:
    """Accuracy and median-error figures with a number: what differs between initial and refined poses."""
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    return numeric and (key.startswith("acc_") or (key.startswith("median_") and key != "median_depth"))


def evaluate_initial_poses(
    scene: Scene,
    records: RefinementRecords,
    query_stats: Mapping[str, QueryStats],
    median_depth: float | None,
) -> dict[str, float | int | None]:
    """Headline figures of the pre-refinement poses, prefixed "initial_", plus the refinement rates.

    Scored by `evaluate_poses` against the same queries and failures as the returned poses, so
    `acc_5cm_5deg` vs `initial_acc_5cm_5deg` is the refinement on/off ablation from one run. When
    queries were answered but none of them has a learned pose (`relocalize.prior=none` computes
    none), the learned pose was not computed: every initial_ figure is None (null in JSON), not the
    0 % and inf errors of a pose that failed everywhere.
    """
    ok = records.success & np.isfinite(records.initial_R).all(axis=(1, 2)) & np.isfinite(records.initial_t).all(axis=1)
    estimates = {n: (records.initial_R[i], records.initial_t[i]) for i, n in enumerate(records.names) if ok[i]}
    summary, _ = evaluate_poses(scene, estimates, query_stats, median_depth)
    computed = initial_pose_computed(records)
    out: dict[str, float | int | None] = {f"initial_{k}": v if computed else None for k, v in summary.items()
                                          if v is not None and _is_headline(k, v)}
    out.update(refinement_summary(records.kept[records.success], records.iterations[records.success]))
    return out


def initial_pose_computed(records: RefinementRecords) -> bool:
    """Whether the learned (pre-refinement) pose was computed: False when queries were answered and
    none of them has one (NaN initial_R/initial_t on every answered query: relocalize.prior=none)."""
    ok = np.isfinite(records.initial_R).all(axis=(1, 2)) & np.isfinite(records.initial_t).all(axis=1)
    return not (records.success.any() and not (ok & records.success).any())
