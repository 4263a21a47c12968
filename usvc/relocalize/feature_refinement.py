"""Refinement by features: the learned pose guides matching of the query's SIFT keypoints to the
SfM model's own landmarks, and LO-RANSAC PnP on those matches gives the exact pose.

Guided pass: the landmarks the prior pose sees (in front, inside the image, and looked at from
within the cone of directions they were mapped from) are projected; each is compared only with
query keypoints within a radius of its projection (nearest descriptor, Lowe's ratio test against
the second nearest there, one landmark per keypoint), and pycolmap's LO-RANSAC absolute pose
with non-linear refinement re-estimates the pose. The radius then shrinks and the pass repeats
from the new pose. When the prior is missing or too far off for the first pass, the query's
keypoints are matched against every landmark (2D-to-3D, ratio test, mutual), PnP gives a pose,
and the remaining guided passes tighten it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from usvc.core.geometry import camera_centers
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.pnp import project_points, solve_pnp
from usvc.relocalize.query_features import QueryFeatures

log = logging.getLogger(__name__)

_CHUNK = 2048  # rows of a descriptor-distance block (memory ~ CHUNK x keypoints x 4 bytes)
_PAIRS = 65536  # (landmark, keypoint) pairs compared at a time in guided matching
_DENSE_SIMILARITY = 8_000_000  # up to this many landmark x keypoint entries (32 MB), one matrix product


@dataclass(frozen=True)
class FeatureMatchOptions:
    """Guided-matching parameters, from the `features_*` fields of RelocalizeOptions."""

    radii_px: tuple[float, ...]  # search radius of each guided pass, px of the feature image
    ratio: float  # Lowe's ratio: nearest descriptor distance < ratio x second nearest
    max_error_px: float  # LO-RANSAC inlier threshold, px of the feature image
    min_inliers: int  # fewer PnP inliers than this: the pass failed
    view_margin_deg: float  # a landmark is matched up to this many degrees outside its mapped viewing cone


@dataclass
class FeatureResult:
    """What refinement by features found. `path` is "guided" (from the learned pose), "global"
    (matching against every landmark, then guided passes) or "" (no pose)."""

    R: np.ndarray | None
    t: np.ndarray | None
    inliers: int = 0  # PnP inliers of the returned pose
    matches: int = 0  # correspondences that PnP saw in the last accepted pass
    path: str = ""
    passes: list[dict] = field(default_factory=list)  # per pass: kind, radius, matches, inliers
    match_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the last accepted pass's matches
    match_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    why: str = ""  # why no pose, when there is none

    @property
    def success(self) -> bool:
        return self.R is not None


def visible_landmarks(landmarks: Landmarks, camera: Camera, R: np.ndarray, t: np.ndarray,
                      margin_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices, projected uv) of the landmarks a camera at (R, t) can see: in front of it, inside
    the image, and viewed from within their mapped viewing cone widened by `margin_deg`."""
    uv, depth = project_points(camera, landmarks.xyz, R, t)
    ok = (depth > 0) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    center = camera_centers(R, t)
    ray = center[None] - landmarks.xyz
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", ray, landmarks.view_dir), -1.0, 1.0)))
    ok &= angle <= np.minimum(landmarks.view_angle_deg + margin_deg, 180.0)
    idx = np.flatnonzero(ok)
    return idx, uv[idx]


def _best_two(sim: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of a similarity block: the column of the largest entry, the largest and the second
    largest (-inf when the row has one column). Two passes over the block, no sort."""
    rows = np.arange(len(sim))
    first = np.argmax(sim, axis=1)
    s1 = sim[rows, first]
    if sim.shape[1] == 1:
        return first, s1, np.full(len(sim), -np.inf, dtype=sim.dtype)
    masked = sim.copy()
    masked[rows, first] = -np.inf
    return first, s1, masked.max(axis=1)


def _distance(sim: np.ndarray) -> np.ndarray:
    """Euclidean distance of unit descriptors from their dot product (inf for -inf)."""
    return np.where(np.isfinite(sim), np.sqrt(np.maximum(2.0 - 2.0 * sim, 0.0)), np.inf).astype(np.float32)


def _one_to_one(rows: np.ndarray, cols: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for every column, only its closest row (ties: the first)."""
    order = np.lexsort((dist, cols))
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = cols[order][1:] != cols[order][:-1]
    sel = np.sort(order[keep])
    return rows[sel], cols[sel]


def guided_matches(lm_uv: np.ndarray, lm_desc: np.ndarray, feats: QueryFeatures, radius: float,
                   ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows) matched within `radius` px of each landmark's projection.

    Only the (landmark, keypoint) pairs within the radius are compared: a kd-tree lists them, their
    descriptor distances are computed pair by pair, and each landmark's nearest and second nearest
    keypoint come from a segmented maximum over its pairs (no landmarks x keypoints matrix)."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(lm_uv) == 0 or len(feats) == 0:
        return empty
    pairs = cKDTree(lm_uv).sparse_distance_matrix(cKDTree(feats.uv), radius, output_type="ndarray")
    if len(pairs) == 0:
        return empty
    key = pairs["i"].astype(np.int64) * len(feats) + pairs["j"]
    order = np.argsort(key)  # by landmark, then keypoint (unique keys): the same order every run
    lm, kp = pairs["i"][order].astype(np.int64), pairs["j"][order].astype(np.int64)
    starts = np.flatnonzero(np.r_[True, lm[1:] != lm[:-1]])
    rows_with, counts = lm[starts], np.diff(np.r_[starts, len(lm)])
    if len(rows_with) * len(feats) <= _DENSE_SIMILARITY:  # one product, then a gather: fastest
        sim = (lm_desc[rows_with] @ feats.descriptor.T)[np.repeat(np.arange(len(rows_with)), counts), kp]
    else:
        sim = np.empty(len(kp), np.float32)
        for a in range(0, len(kp), _PAIRS):  # bounded memory: _PAIRS x 128 floats per side
            b = min(a + _PAIRS, len(kp))
            sim[a:b] = np.einsum("ij,ij->i", lm_desc[lm[a:b]], feats.descriptor[kp[a:b]])
    best = np.maximum.reduceat(sim, starts)
    is_best = sim == np.repeat(best, counts)
    # the first pair of each landmark that reaches its best similarity
    first = np.flatnonzero(is_best)
    first = first[np.concatenate([[True], lm[first][1:] != lm[first][:-1]])]
    masked = sim.copy()
    masked[first] = -np.inf
    second = np.maximum.reduceat(masked, starts)  # -inf for a landmark with one candidate
    d1 = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
    d2 = np.where(np.isfinite(second), np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0)), np.inf)
    ok = d1 < ratio * d2
    return _one_to_one(rows_with[ok], kp[first][ok], d1[ok])


def global_matches(lm_desc: np.ndarray, feats: QueryFeatures, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows): each keypoint's nearest landmark by descriptor, ratio test
    against the second nearest landmark, mutual (the keypoint is also the landmark's nearest)."""
    k = len(feats)
    if k == 0 or len(lm_desc) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    best_s = np.full((k, 2), -np.inf, dtype=np.float32)  # each keypoint's two largest similarities so far
    best_i = np.zeros(k, dtype=np.int64)
    lm_best = np.zeros(len(lm_desc), dtype=np.int64)
    for start in range(0, len(lm_desc), _CHUNK):
        sim = feats.descriptor @ lm_desc[start:start + _CHUNK].T  # (K, chunk): per keypoint along rows
        lm_best[start:start + sim.shape[1]] = np.argmax(sim, axis=0)
        first, s1, s2 = _best_two(sim)
        new_first = s1 > best_s[:, 0]
        best_i = np.where(new_first, first + start, best_i)
        cand = np.stack([best_s[:, 0], best_s[:, 1], s1, s2], axis=1)
        cand.sort(axis=1)
        best_s = cand[:, :1:-1]  # the two largest, largest first
    d1, d2 = _distance(best_s[:, 0]), _distance(best_s[:, 1])
    ok = np.isfinite(d1) & (d1 < ratio * d2)
    ok &= lm_best[best_i] == np.arange(k)
    cols = np.flatnonzero(ok)
    return best_i[cols], cols


def _pnp(uv: np.ndarray, xyz: np.ndarray, camera: Camera, opts: FeatureMatchOptions, seed: int):
    if len(uv) < max(opts.min_inliers, 4):
        return None
    res = solve_pnp(uv, xyz, camera, max_error_px=opts.max_error_px, seed=seed, min_inliers=opts.min_inliers,
                    backend="pycolmap")
    return res if res.success else None


def refine_by_features(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
                       R0: np.ndarray | None, t0: np.ndarray | None, opts: FeatureMatchOptions,
                       seed: int = 0) -> FeatureResult:
    """The pose of the query whose features are `feats` (pixels of `camera`'s image), starting from
    the learned pose (R0, t0) when there is one; `lm_desc` are the landmarks' unit descriptors."""
    out = FeatureResult(None, None)
    R, t = R0, t0
    start_pass = 0
    if R is not None and t is not None:
        idx, uv = visible_landmarks(landmarks, camera, R, t, opts.view_margin_deg)
        li, ki = guided_matches(uv, lm_desc[idx], feats, opts.radii_px[0], opts.ratio)
        res = _pnp(feats.uv[ki], landmarks.xyz[idx[li]], camera, opts, seed)
        out.passes.append({"kind": "guided", "radius_px": opts.radii_px[0], "candidates": int(len(idx)),
                           "matches": int(len(li)), "inliers": 0 if res is None else res.num_inliers})
        if res is not None:
            out.path, start_pass = "guided", 1
            R, t = res.R, res.t
            out.inliers, out.matches = res.num_inliers, len(li)
            out.match_uv, out.match_xyz = feats.uv[ki], landmarks.xyz[idx[li]]
    if not out.path:
        li, ki = global_matches(lm_desc, feats, opts.ratio)
        res = _pnp(feats.uv[ki], landmarks.xyz[li], camera, opts, seed)
        out.passes.append({"kind": "global", "radius_px": None, "candidates": int(len(landmarks)),
                           "matches": int(len(li)), "inliers": 0 if res is None else res.num_inliers})
        if res is None:
            out.why = (f"features: {len(li)} matches to landmarks, no pose with {opts.min_inliers} inliers "
                       f"within {opts.max_error_px:g} px")
            return out
        out.path, start_pass = "global", 1
        R, t = res.R, res.t
        out.inliers, out.matches = res.num_inliers, len(li)
        out.match_uv, out.match_xyz = feats.uv[ki], landmarks.xyz[li]
    for radius in opts.radii_px[start_pass:]:
        idx, uv = visible_landmarks(landmarks, camera, R, t, opts.view_margin_deg)
        li, ki = guided_matches(uv, lm_desc[idx], feats, radius, opts.ratio)
        res = _pnp(feats.uv[ki], landmarks.xyz[idx[li]], camera, opts, seed)
        out.passes.append({"kind": "guided", "radius_px": radius, "candidates": int(len(idx)),
                           "matches": int(len(li)), "inliers": 0 if res is None else res.num_inliers})
        if res is None or res.num_inliers < out.inliers // 2:
            break  # keep the last pose: a tighter radius that loses most support is not better
        R, t = res.R, res.t
        out.inliers, out.matches = res.num_inliers, len(li)
        out.match_uv, out.match_xyz = feats.uv[ki], landmarks.xyz[idx[li]]
    out.R, out.t = np.asarray(R, np.float64).copy(), np.asarray(t, np.float64).copy()
    return out
