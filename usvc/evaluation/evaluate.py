"""Score estimated query poses against a scene's ground truth, per query and in summary.

The summary follows `pose_errors.summarize` (ACE's rules); the per-query rows keep what the
summary throws away (which query failed, how far off each one was, where its camera is) so
plots and failure analysis need no second pass over the inputs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from usvc.errors import UsvcError
from usvc.evaluation.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.geometry import camera_centers
from usvc.scene import Scene

PER_QUERY_COLUMNS: tuple[str, ...] = (
    "name", "rot_deg", "trans", "trans_cm", "failed", "inliers",
    "gt_x", "gt_y", "gt_z", "est_x", "est_y", "est_z",
)


@dataclass(frozen=True)
class QueryStats:
    """What the relocalize stage reports for one query besides its pose."""

    inliers: int
    seconds: float  # total time for this query
    success: bool


def read_query_stats(path: Path | str) -> dict[str, QueryStats]:
    """Read `queries.h5` (datasets name, inliers, seconds, success) into {name: QueryStats}."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"query statistics not found: {path} (run the relocalize stage first)")
    with h5py.File(path, "r") as h5:
        missing = [k for k in ("name", "inliers", "seconds", "success") if k not in h5]
        if missing:
            raise UsvcError(f"{path}: missing dataset(s) {missing}")
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["name"][()]]
        inliers, seconds, success = h5["inliers"][()], h5["seconds"][()], h5["success"][()]
    if not (len(names) == len(inliers) == len(seconds) == len(success)):
        raise UsvcError(f"{path}: datasets name/inliers/seconds/success differ in length "
                        f"({len(names)}, {len(inliers)}, {len(seconds)}, {len(success)})")
    if len(set(names)) != len(names):
        raise UsvcError(f"{path}: duplicate query names")
    return {n: QueryStats(int(i), float(s), bool(ok)) for n, i, s, ok in zip(names, inliers, seconds, success)}


def _check_names(kind: str, names: Any, queries: set[str], scene: str) -> None:
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
    _check_names("poses file", estimates, names, scene.name)
    _check_names("query statistics", query_stats, names, scene.name)
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

    summary = summarize(rot, trans, scene.metric_scale, median_depth, failed,
                        ms_per_query=1000.0 * float(np.mean([s.seconds for s in query_stats.values()])))
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
