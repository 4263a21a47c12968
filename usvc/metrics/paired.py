"""Two methods' answers to the same queries, compared query by query.

A scene's test split has 8-25 queries, so a threshold's share moves by 4-13 points per query and a
median by whichever query falls in its place: two methods' figures differ on such a split whether
or not one is the better. A paired comparison says how much of a difference the queries support:
every figure of `summarize` (the shares at each threshold, the medians) for both methods, their
difference, and a paired bootstrap interval for it (the queries resampled with replacement, both
methods scored on the same resample, the percentile interval of the differences), and one for the
ratio of the two median translations (the form "within 1.1x of the baseline" takes); and, query by
query, on how many each method is the closer to the ground truth (translation, then rotation on
ties), with the two-sided sign test's p-value over the queries where they differ. A query without
an answer is infinitely wrong, as in `summarize`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.core.scene import Scene
from usvc.metrics.evaluate import check_query_names

# The figures compared: every share and median `summarize` reports, where the scene has them
FIGURES = ("acc_10cm_5deg", "acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "acc_rel_5cm_5deg", "acc_rel_2cm_2deg",
           "acc_rel_1cm_1deg", "median_trans_cm", "median_trans_rel_cm", "median_rot_deg")


@dataclass(frozen=True)
class QueryErrors:
    """One method's errors on a scene's test queries, in the split's order (inf: no answer)."""

    names: tuple[str, ...]
    rot_deg: np.ndarray
    trans: np.ndarray  # scene units

    @property
    def failed(self) -> np.ndarray:
        return ~(np.isfinite(self.rot_deg) & np.isfinite(self.trans))


def query_errors(scene: Scene, estimates: Mapping[str, tuple[np.ndarray, np.ndarray]], what: str) -> QueryErrors:
    """Errors of `estimates` ({query name: (R, t)}; a missing query is unanswered) against the
    scene's ground truth. `what` names the estimates in the error raised for a name that is not a
    test query of the scene."""
    queries = scene.split("test")
    if not scene.has_poses:
        raise UsvcError(f"scene {scene.name!r} has no ground-truth poses to compare against")
    check_query_names(what, estimates, {f.name for f in queries}, scene.name)
    has = np.array([f.name in estimates for f in queries])
    R = np.stack([estimates[f.name][0] if f.name in estimates else np.eye(3) for f in queries])
    t = np.stack([estimates[f.name][1] if f.name in estimates else np.zeros(3) for f in queries])
    R_gt, t_gt = np.stack([f.R for f in queries]), np.stack([f.t for f in queries])
    rot = np.where(has, rotation_error_deg(R, R_gt), np.inf)
    trans = np.where(has, translation_error(R, t, R_gt, t_gt), np.inf)
    rot[~np.isfinite(rot)] = np.inf
    trans[~np.isfinite(trans)] = np.inf
    return QueryErrors(tuple(f.name for f in queries), rot, trans)


def _figures(errors: QueryErrors, idx: np.ndarray, metric_scale: float | None,
             median_depth: float | None) -> dict[str, float]:
    s = summarize(errors.rot_deg[idx], errors.trans[idx], metric_scale, median_depth, errors.failed[idx])
    return {k: float(s[k]) for k in (*FIGURES, "median_trans") if s.get(k) is not None}  # type: ignore[arg-type]


def _ratio(x: float, y: float) -> float:
    """x / y for medians: inf where y is 0 and x is not, 1 where both are (the same answers)."""
    if x == y:
        return 1.0
    return x / y if y > 0 else math.inf


def sign_test_p(wins: int, losses: int) -> float:
    """Two-sided exact sign test: the chance of a split at least this uneven between two methods
    that are each the closer with probability 1/2 (ties left out)."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(wins, losses) + 1)) / 2.0 ** n
    return min(1.0, 2.0 * tail)


def paired_comparison(a: QueryErrors, b: QueryErrors, metric_scale: float | None, median_depth: float | None,
                      resamples: int = 10_000, level: float = 0.95, seed: int = 0) -> dict[str, Any]:
    """Method `a` against method `b` on the same queries: for each figure, a's and b's value, the
    difference a - b and its paired bootstrap interval at `level` (`resamples` resamples of the
    queries, drawn with `seed`: the same interval every run); query by query, on how many a (b)
    is the closer and the sign test's p-value. An interval with an infinite end (a resample where
    more than half of a method's answers are missing) is reported as None."""
    if a.names != b.names:
        raise UsvcError("paired comparison: the two methods' errors are not of the same queries in the same order")
    if resamples < 1:
        raise UsvcError(f"paired comparison: resamples must be at least 1, got {resamples}")
    if not 0 < level < 1:
        raise UsvcError(f"paired comparison: level must be in (0, 1), got {level}")
    n = len(a.names)
    whole = np.arange(n)
    fa, fb = _figures(a, whole, metric_scale, median_depth), _figures(b, whole, metric_scale, median_depth)
    keys = [k for k in FIGURES if k in fa and k in fb]  # median_trans (scene units) only for the ratio
    rng = np.random.default_rng(seed)
    diffs = np.empty((resamples, len(keys)))
    ratios = np.empty(resamples)  # a's median translation over b's
    for r in range(resamples):
        idx = rng.integers(0, n, n)
        ra, rb = _figures(a, idx, metric_scale, median_depth), _figures(b, idx, metric_scale, median_depth)
        diffs[r] = [ra[k] - rb[k] for k in keys]
        ratios[r] = _ratio(ra["median_trans"], rb["median_trans"])
    lo_q, hi_q = 100 * (1 - level) / 2, 100 * (1 + level) / 2
    figures = {}
    for j, k in enumerate(keys):
        col = diffs[:, j]
        finite = bool(np.all(np.isfinite(col)))
        lo, hi = (float(np.percentile(col, lo_q)), float(np.percentile(col, hi_q))) if finite else (None, None)
        diff = fa[k] - fb[k]
        figures[k] = {"a": fa[k], "b": fb[k], "difference": diff if math.isfinite(diff) else None,
                      "interval": [lo, hi]}
    # query by query: translation error first, rotation where the translations are equal
    closer_a = (a.trans < b.trans) | ((a.trans == b.trans) & (a.rot_deg < b.rot_deg))
    closer_b = (b.trans < a.trans) | ((a.trans == b.trans) & (b.rot_deg < a.rot_deg))
    wins, losses = int(closer_a.sum()), int(closer_b.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = a.trans / b.trans
    finite_ratio = ratio[np.isfinite(ratio)]
    ratio_of_medians = _ratio(fa["median_trans"], fb["median_trans"])
    finite = bool(np.all(np.isfinite(ratios)))
    return {"queries": n, "level": level, "resamples": resamples, "seed": seed,
            "failed": {"a": int(a.failed.sum()), "b": int(b.failed.sum())},
            "figures": figures,
            "median_translation_over": {"value": ratio_of_medians if math.isfinite(ratio_of_medians) else None,
                                        "interval": [float(np.percentile(ratios, lo_q)),
                                                     float(np.percentile(ratios, hi_q))] if finite else [None, None]},
            "per_query": {"a_closer": wins, "b_closer": losses, "equal": n - wins - losses,
                          "sign_test_p": sign_test_p(wins, losses),
                          "median_translation_ratio": float(np.median(finite_ratio)) if len(finite_ratio) else None}}
