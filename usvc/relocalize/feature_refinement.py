"""Refinement by features: the learned pose guides matching of the query's SIFT keypoints to the
SfM model's own landmarks, and LO-RANSAC PnP on those matches gives the exact pose.

Hypotheses, in order of cost (`Relocalizer` decides which run; the one with the most support wins):

Guided pass: the landmarks the prior pose sees (in front, inside the image, and looked at from
within the cone of directions they were mapped from) are projected; each is compared only with
query keypoints within a radius of its projection (nearest descriptor, Lowe's ratio test against
the second nearest there, one landmark per keypoint), and pycolmap's LO-RANSAC absolute pose
with non-linear refinement re-estimates the pose. The radius then shrinks and the pass repeats
from the new pose. When the prior is missing or too far off for the first pass, the query's
keypoints are matched against every landmark (2D-to-3D, ratio test, mutual), PnP gives a pose,
and the remaining guided passes tighten it; and the query is matched as SIFT + PnP matches it
(`verified_matching`: every mapping image's observed keypoints, verified per pair, lifted through
the tracks), PnP, then the same guided passes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from usvc.core.geometry import camera_centers
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.byte_products import (
    DOT_SCALE,
    MASKED,
    ByteRows,
    ProductBlocks,
    dots,
)
from usvc.relocalize.device_matching import best_two_and_column_max, masked_row_best_two
from usvc.relocalize.options import REFERENCE_SHORT_SIDE, RelocalizeOptions
from usvc.relocalize.pnp import in_image, project_points, solve_pnp
from usvc.relocalize.query_cores import products_on_own_threads
from usvc.relocalize.query_features import QueryFeatures
from usvc.relocalize.tiled_matching import row_best_two_within, tiles_pay
from usvc.relocalize.verified_matching import VerifiedMatches

log = logging.getLogger(__name__)

# SIFT + PnP's inlier threshold for a query's pose, px at the mapping images' size: the value with
# which benchmarks/baseline_sift.py registers queries (usvc.sfm.posing.QUERY_MAX_ERROR_PX; a test
# keeps the two equal without the query step importing the SfM step)
VERIFIED_MAX_ERROR_PX = 4.0
_CHUNK = 2048  # rows of a descriptor-distance block (memory ~ CHUNK x keypoints x 4 bytes)
_PAIRS = 65536  # (landmark, keypoint) pairs compared at a time in guided matching
_DENSE_SIMILARITY = 8_000_000  # up to this many landmark x keypoint entries (32 MB), one matrix product on a device
_DENSE_PAIR_SHARE = 16  # guided matching on a device: one product when the pairs in reach are >= 1/16 of its entries
# Guided matching on the CPU: a pair in reach compared on its own (kd-tree, gathers, segmented maxima)
# costs about as much as this many entries of a tile's product (`tiled_matching`); tiles where
# they compute fewer such costs (mini at 640 x 480: its first pass 44 -> 12 ms, second 15 -> 10 ms)
_TILE_PAIR_COST = 40.0
# The fewest LO-RANSAC trials of a feature PnP (COLMAP's default floor: 100). Guided matches are
# nearly all inliers (mini's ~1,000 a pass: 99 %), where RANSAC's adaptive stop needs a handful of
# trials and the floor made every pass run 100, each scored on every match: 20 took ~4 ms off each
# PnP (of ~13) with the same poses (docs/speed.md). Where inliers are few the adaptive count rules.
FEATURE_MIN_TRIALS = 20
# A guided answer that explains fewer than this share of the matches to every landmark that their
# own pose (P4Pf) explains was found from a wrong start (a learned pose off by ~10 degrees led bird's
# guided passes to a pose 6.5 degrees off with 218 inliers, explaining 33 of 76): the matches to
# every landmark then get their own hypothesis. Right answers explained 0.93-1.01 of them on office,
# bird and mini, from learned poses right or turned by up to 30 degrees (docs/results.md).
AGREEMENT = 0.8


@dataclass(frozen=True)
class FeatureMatchOptions:
    """Guided-matching parameters, from the `features_*` fields of RelocalizeOptions."""

    radii_px: tuple[float, ...]  # search radius of each guided pass, px of the feature image
    ratio: float  # Lowe's ratio: nearest descriptor distance < ratio x second nearest
    max_error_px: float  # LO-RANSAC inlier threshold, px of the feature image
    min_inliers: int  # fewer PnP inliers than this: the pass failed
    view_margin_deg: float  # a landmark is matched up to this many degrees outside its mapped viewing cone
    device: str | None = None  # the torch device of the descriptor products (None: numpy, on the CPU)
    final: str = "confirmed"  # the answer's last pass: confirmed (`confirmed_pass`) | guided (none) | images (`images_pass`)
    threads: int = 1  # the query's threads: SIFT + PnP's pairs and the images pass's images side by side on them
    pnp: str = "poselib"  # the passes' LO-RANSAC PnP backend (`pnp.solve_pnp`): poselib | pycolmap
    final_images: int = 32  # the last pass's mapping images, the most covisible first (0: every one)


def feature_options(options: RelocalizeOptions, short_side: int, device: str | None = None,
                    threads: int = 1) -> FeatureMatchOptions:
    """The relocalize options' features_* settings in px of an image whose short side is `short_side`;
    the descriptor products on the torch `device` (None: numpy on the CPU); the query's `threads`."""
    scale = short_side / REFERENCE_SHORT_SIDE
    return FeatureMatchOptions(radii_px=tuple(float(r) * scale for r in options.features_radii_px),
                               ratio=options.features_ratio, max_error_px=options.features_max_error_px * scale,
                               min_inliers=options.features_min_inliers,
                               view_margin_deg=options.features_view_margin_deg, device=device,
                               final=options.features_final, threads=threads, pnp=options.features_pnp,
                               final_images=options.features_final_images)


@dataclass
class FeatureResult:
    """What refinement by features found. `path` is "guided" (from the learned pose), "global"
    (matching against every landmark's descriptor, then guided passes), "verified" (SIFT + PnP's
    evidence: matches to each mapping image, verified per pair, lifted through the tracks; then
    guided passes) or "" (no pose). `R`, `t` are world-to-camera (x_cam = R x_world + t), None
    when no pose was found."""

    R: np.ndarray | None
    t: np.ndarray | None
    inliers: int = 0  # PnP inliers of the returned pose
    matches: int = 0  # correspondences that PnP saw in the last accepted pass
    path: str = ""
    passes: list[dict] = field(default_factory=list)  # per pass: kind, radius, matches, inliers
    match_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the last accepted pass's matches
    match_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    match_landmark: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # their landmark rows
    why: str = ""  # why no pose, when there is none
    tried: list[dict] = field(default_factory=list)  # per hypothesis tried: its path and its support
    verified: dict | None = None  # what SIFT + PnP's matching took, when it ran (VerifiedMatches.record)
    verified_seconds: float | None = None  # its time
    agreement: dict | None = None  # a guided answer checked against the matches to every landmark (refine_by_features)
    match_keypoint: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # the matches' query keypoint rows

    @property
    def success(self) -> bool:
        return self.R is not None


def visible_landmarks(landmarks: Landmarks, camera: Camera, R: np.ndarray, t: np.ndarray,
                      margin_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices, projected uv) of the landmarks a camera at (R, t) can see: in front of it, inside
    the image, and viewed from within their mapped viewing cone widened by `margin_deg`."""
    uv, depth = project_points(camera, landmarks.xyz, R, t)
    near = np.flatnonzero(in_image(camera, uv, depth))  # the viewing cone is tested on these only (a view sees a fraction of the map)
    ray = camera_centers(R, t)[None] - landmarks.xyz[near]
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", ray, landmarks.view_dir[near]), -1.0, 1.0)))
    idx = near[angle <= np.minimum(landmarks.view_angle_deg[near] + margin_deg, 180.0)]
    return idx, uv[idx]


def _distance(sim: np.ndarray) -> np.ndarray:
    """Euclidean distance of (near-)unit descriptors from their dot product (inf for -inf)."""
    return np.where(np.isfinite(sim), np.sqrt(np.maximum(2.0 - 2.0 * sim, 0.0)), np.inf).astype(np.float32)


def _one_to_one(rows: np.ndarray, cols: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for every column, only its closest row (ties: the first)."""
    order = np.lexsort((dist, cols))
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = cols[order][1:] != cols[order][:-1]
    sel = np.sort(order[keep])
    return rows[sel], cols[sel]


def _ratio_test(s1: np.ndarray, s2: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(passes Lowe's ratio test, nearest distance) from the two largest similarities."""
    d1, d2 = _distance(s1), _distance(s2)
    return np.isfinite(d1) & (d1 < ratio * d2), d1


def guided_matches(lm_uv: np.ndarray, lm_desc: np.ndarray, feats: QueryFeatures, radius: float,
                   ratio: float, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows) matched within `radius` px of each landmark's projection:
    each landmark's nearest keypoint by descriptor among those within the radius (the first on
    ties), Lowe's ratio test against the second nearest there, one landmark per keypoint.

    On the CPU, where the pairs in reach are many (a wide radius), landmarks and keypoints are
    binned into tiles and each tile's landmarks compared with the keypoints around it
    (`tiled_matching`). Otherwise a kd-tree lists the pairs within the radius: where they are
    few, only the pairs' descriptors are compared, and a segmented maximum over each landmark's
    pairs finds its nearest two; with a torch `device` and many pairs, one landmarks x keypoints
    product there gives every similarity, the pairs outside the radius masked (`device_matching`)."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(lm_uv) == 0 or len(feats) == 0:
        return empty
    if device is None and tiles_pay(lm_uv, feats.uv, radius, _TILE_PAIR_COST):
        first, s1, s2 = row_best_two_within(lm_uv, lm_desc, feats.uv, feats.scaled, radius)
        ok, d1 = _ratio_test(s1, s2, ratio)
        rows = np.flatnonzero(ok)
        return _one_to_one(rows, first[rows], d1[rows])
    pairs = cKDTree(lm_uv).sparse_distance_matrix(cKDTree(feats.uv), radius, output_type="ndarray")
    if len(pairs) == 0:
        return empty
    lm, kp = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    cells = len(lm_uv) * len(feats)
    if device is not None and cells <= _DENSE_SIMILARITY and len(lm) * _DENSE_PAIR_SHARE >= cells:
        first, s1, s2 = masked_row_best_two(lm_desc, feats.scaled, lm, kp, device)
        ok, d1 = _ratio_test(s1, s2, ratio)  # a landmark with no keypoint in reach has s1 = -inf: fails
        rows = np.flatnonzero(ok)
        return _one_to_one(rows, first[rows], d1[rows])
    order = np.argsort(lm * len(feats) + kp)  # by landmark, then keypoint (unique keys): the same order every run
    lm, kp = lm[order], kp[order]
    starts = np.flatnonzero(np.r_[True, lm[1:] != lm[:-1]])
    rows_with, counts = lm[starts], np.diff(np.r_[starts, len(lm)])
    sim = np.empty(len(kp), np.float32)
    for a in range(0, len(kp), _PAIRS):  # bounded memory: _PAIRS x 128 floats per side
        b = min(a + _PAIRS, len(kp))
        sim[a:b] = np.einsum("ij,ij->i", lm_desc[lm[a:b]], feats.scaled[kp[a:b]])
    best = np.maximum.reduceat(sim, starts)
    # the first pair of each landmark that reaches its best similarity
    first = np.flatnonzero(sim == np.repeat(best, counts))
    first = first[np.concatenate([[True], lm[first][1:] != lm[first][:-1]])]
    sim[first] = -np.inf
    second = np.maximum.reduceat(sim, starts)  # -inf for a landmark with one candidate
    ok, d1 = _ratio_test(best, second, ratio)
    return _one_to_one(rows_with[ok], kp[first][ok], d1[ok])


def global_matches(lm_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                   lm_bytes: ByteRows | None = None, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`landmark_matches` against every landmark, or only against landmark `rows` (sorted: those the
    mapping photos retrieved for the query observe, `image_retrieval`), the landmark rows returned
    being rows of the whole table either way."""
    if rows is None:
        return landmark_matches(lm_desc, feats, ratio, device, lm_bytes)
    li, ki = landmark_matches(lm_desc[rows], feats, ratio, device, None if lm_bytes is None else lm_bytes.take(rows))
    return rows[li], ki


def landmark_matches(lm_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                     lm_bytes: ByteRows | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows): each keypoint's nearest landmark by descriptor, ratio test
    against the second nearest landmark, mutual (the keypoint is also the landmark's nearest: the
    first keypoint that reaches the landmark's largest similarity). `lm_desc`: the landmarks'
    bytes as `byte_products.scaled` rows, whose products are their integer dots / 512²; on the CPU
    those integers come from `byte_products.dots` on `lm_bytes`, the same bytes held for it (made
    from `lm_desc` when not given: a caller holds them once per map), as int8 products where the
    CPU has them. With a torch `device` the products of the scaled rows and their reductions run
    there (`device_matching`): the same similarities."""
    k = len(feats)
    if k == 0 or len(lm_desc) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if device is not None:
        best_s, best_i, lm_max = best_two_and_column_max(feats.scaled, lm_desc, device)
    else:
        if lm_bytes is None:
            lm_bytes = ByteRows.of(np.rint(np.asarray(lm_desc, np.float64) * 512.0).astype(np.uint8))
        best_s = np.full((k, 2), -np.inf, dtype=np.float32)  # each keypoint's two largest similarities so far
        best_i = np.zeros(k, dtype=np.int64)
        lm_max = np.empty(len(lm_desc), dtype=np.float32)  # each landmark's largest similarity to a keypoint
        query = ByteRows.of(feats.codes, lm_bytes.signed is not None)
        blocks = ProductBlocks(k * min(_CHUNK, len(lm_desc)))  # one block's products, reused: a fresh
        with products_on_own_threads():  # multi-MB array per block costs its page faults; int8: this thread alone
            for start in range(0, len(lm_desc), _CHUNK):
                stop = min(start + _CHUNK, len(lm_desc))
                sim = dots(query, lm_bytes.rows_between(start, stop), blocks)  # (K, chunk): exact integers
                lm_max[start:stop] = sim.max(axis=0).astype(np.float32) / np.float32(DOT_SCALE)
                first, s1, s2 = _row_best_two(sim)  # per keypoint along rows
                best_i = np.where(s1 > best_s[:, 0], first + start, best_i)
                cand = np.stack([best_s[:, 0], best_s[:, 1], s1, s2], axis=1)
                cand.sort(axis=1)
                best_s = cand[:, :1:-1]  # the two largest, largest first
    reach = np.flatnonzero(best_s[:, 0] == lm_max[best_i])  # keypoints that reach their landmark's largest ...
    _, once = np.unique(best_i[reach], return_index=True)  # ... the first of them per landmark: mutual
    ok, _ = _ratio_test(best_s[:, 0], best_s[:, 1], ratio)
    mutual = np.zeros(k, dtype=bool)
    mutual[reach[once]] = True
    cols = np.flatnonzero(ok & mutual)
    return best_i[cols], cols


def _row_best_two(sim: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of a block of integer dots of bytes (`byte_products.dots`): the column of the largest
    entry (the first on ties), the largest and the second largest as the scaled rows' similarities
    (float32, / 512²: exact; -inf where the row has no other). Overwrites each row's largest entry:
    reductions along rows only, the contiguous (fast) direction, and no copy."""
    rows = np.arange(len(sim))
    first = np.argmax(sim, axis=1)
    s1 = sim[rows, first]
    sim[rows, first] = MASKED  # below every dot of bytes
    s2 = sim.max(axis=1) if sim.shape[1] > 1 else np.full(len(sim), MASKED, sim.dtype)
    scale = np.float32(DOT_SCALE)
    return first, s1.astype(np.float32) / scale, np.where(s2 == MASKED, -np.inf, s2.astype(np.float32) / scale
                                                          ).astype(np.float32)


def _pnp(uv: np.ndarray, xyz: np.ndarray, camera: Camera, opts: FeatureMatchOptions, seed: int):
    if len(uv) < max(opts.min_inliers, 4):
        return None
    res = solve_pnp(uv, xyz, camera, max_error_px=opts.max_error_px, seed=seed, min_inliers=opts.min_inliers,
                    backend=opts.pnp, min_trials=FEATURE_MIN_TRIALS)
    return res if res.success else None


def _guided_pass(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera, R: np.ndarray,
                 t: np.ndarray, radius: float, opts: FeatureMatchOptions, seed: int):
    """One guided pass from (R, t): (PnP result or None, the pass's record, matched keypoint rows, their landmark rows)."""
    idx, uv = visible_landmarks(landmarks, camera, R, t, opts.view_margin_deg)
    li, ki = guided_matches(uv, lm_desc[idx], feats, radius, opts.ratio, opts.device)
    res = _pnp(feats.uv[ki], landmarks.xyz[idx[li]], camera, opts, seed)
    record = {"kind": "guided", "radius_px": radius, "candidates": int(len(idx)), "matches": int(len(li)),
              "inliers": 0 if res is None else res.num_inliers}
    return res, record, ki, idx[li]


def accept(out: FeatureResult, res, feats: QueryFeatures, keypoint: np.ndarray, landmarks: Landmarks,
            rows: np.ndarray, inliers: int | None = None) -> None:
    """`res`'s pose becomes `out`'s, found with the matches of query keypoints `keypoint` to landmarks `rows`."""
    out.R, out.t = np.asarray(res.R, np.float64).copy(), np.asarray(res.t, np.float64).copy()
    out.inliers, out.matches = res.num_inliers if inliers is None else inliers, len(keypoint)
    out.match_uv, out.match_xyz, out.match_landmark = feats.uv[keypoint], landmarks.xyz[rows], rows
    out.match_keypoint = np.asarray(keypoint, np.int64)


def _tighten(out: FeatureResult, landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
             radii: tuple[float, ...], opts: FeatureMatchOptions, seed: int) -> None:
    """Guided passes from `out`'s pose at the given radii, while they keep most of the support."""
    for radius in radii:
        assert out.R is not None and out.t is not None
        res, record, kp, rows = _guided_pass(landmarks, lm_desc, feats, camera, out.R, out.t, radius, opts, seed)
        out.passes.append(record)
        if res is None or res.num_inliers < out.inliers // 2:
            break  # keep the last pose: a tighter radius that loses most support is not better
        accept(out, res, feats, kp, landmarks, rows)


def from_prior(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera, R0: np.ndarray,
               t0: np.ndarray, opts: FeatureMatchOptions, seed: int = 0) -> FeatureResult:
    """Guided passes from the learned pose (R0, t0): the first at the widest radius, then tighter."""
    out = FeatureResult(None, None)
    res, record, kp, rows = _guided_pass(landmarks, lm_desc, feats, camera, R0, t0, opts.radii_px[0], opts, seed)
    out.passes.append(record)
    if res is None:
        out.why = (f"features: the learned pose's guided pass found {record['matches']} matches, no pose with "
                   f"{opts.min_inliers} inliers")
        return out
    out.path = "guided"
    accept(out, res, feats, kp, landmarks, rows)
    _tighten(out, landmarks, lm_desc, feats, camera, opts.radii_px[1:], opts, seed)
    return out


def _from_correspondences(path: str, keypoint: np.ndarray, rows: np.ndarray, record: dict, landmarks: Landmarks,
                          lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera, opts: FeatureMatchOptions,
                          seed: int, repeats: bool = False, tighten: bool = True) -> FeatureResult:
    """PnP on unguided correspondences of query keypoints `keypoint` to landmarks `rows` (`path`
    names them), then guided passes to tighten (unless not `tighten`). Support counts query
    keypoints: where a keypoint may give several correspondences (`repeats`), the distinct
    keypoints among the inliers, as a guided pass counts."""
    out = FeatureResult(None, None)
    uv = feats.uv[keypoint]
    res = _pnp(uv, landmarks.xyz[rows], camera, opts, seed)
    support = None if res is None or not repeats else int(len(np.unique(keypoint[res.inlier_mask])))
    if support is not None and support < opts.min_inliers:
        res = None
    out.passes.append({**record, "inliers": 0 if res is None else (support or res.num_inliers)})
    if res is None:
        out.why = (f"features ({path}): {len(uv)} correspondences, no pose with {opts.min_inliers} inliers "
                   f"within {opts.max_error_px:g} px")
        return out
    out.path = path
    accept(out, res, feats, keypoint, landmarks, rows, support)
    if not tighten:
        return out
    _tighten(out, landmarks, lm_desc, feats, camera, opts.radii_px[1:], opts, seed)
    return out


def from_global(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
                opts: FeatureMatchOptions, seed: int = 0,
                matches: tuple[np.ndarray, np.ndarray] | None = None, candidates: int | None = None) -> FeatureResult:
    """The query's keypoints matched against every landmark's one descriptor (`matches`, when
    already computed: `global_matches`' landmark and keypoint rows, against `candidates` landmarks:
    those of the photos retrieved for the query), PnP, then tightened."""
    li, ki = matches if matches is not None else global_matches(lm_desc, feats, opts.ratio, opts.device)
    record = {"kind": "global", "radius_px": None, "matches": int(len(li)),
              "candidates": int(len(landmarks) if candidates is None or matches is None else candidates)}
    return _from_correspondences("global", ki, li, record, landmarks, lm_desc, feats, camera, opts, seed)


def from_verified(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
                  verified: VerifiedMatches, opts: FeatureMatchOptions, seed: int = 0) -> FeatureResult:
    """SIFT + PnP's evidence (`verified_matches`) and its PnP: COLMAP's LO-RANSAC with refinement at
    VERIFIED_MAX_ERROR_PX (at the mapping images' size), as SIFT + PnP registers a query. Not
    tightened by guided passes: a keypoint matched in several mapping images counts once per image
    here, a weighting the one descriptor per landmark of a guided pass loses (on mini the guided
    passes moved the median answer from 0.056 to 0.066 cm, SIFT + PnP's being 0.049)."""
    record = {"kind": "verified", "radius_px": None, "candidates": int(verified.images),
              "matches": int(len(verified)), "verified_pairs": int(verified.verified_pairs)}
    scale = min(camera.width, camera.height) / landmarks.image_short_side
    strict = replace(opts, max_error_px=VERIFIED_MAX_ERROR_PX * scale, pnp="pycolmap")  # COLMAP's, as SIFT + PnP's
    return _from_correspondences("verified", verified.keypoint, verified.landmark, record, landmarks, lm_desc, feats,
                                 camera, strict, seed, repeats=True, tighten=False)


def best_hypothesis(hypotheses: list[FeatureResult]) -> FeatureResult:
    """The hypothesis with the most PnP inliers after tightening (the first, the cheapest, on ties),
    carrying every hypothesis's passes and support in its record; or the last failure."""
    found = [h for h in hypotheses if h.success]
    best = max(found, key=lambda h: h.inliers) if found else FeatureResult(None, None)
    best = FeatureResult(best.R, best.t, best.inliers, best.matches, best.path, [], best.match_uv, best.match_xyz,
                         best.match_landmark, best.why, match_keypoint=best.match_keypoint)
    for h in hypotheses:
        best.passes.extend(h.passes)
    best.tried = [{"path": h.path or h.passes[0]["kind"], "inliers": h.inliers if h.success else 0,
                   **(h.agreement or {})} for h in hypotheses if h.passes]
    if not found:
        best.why = "; ".join(h.why for h in hypotheses if h.why) or "features: no match to the landmarks"
    return best


def refine_by_features(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
                       R0: np.ndarray | None, t0: np.ndarray | None, opts: FeatureMatchOptions, seed: int = 0,
                       verified: Callable[[], VerifiedMatches | None] | None = None, use_global: bool = True,
                       global_pairs: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
                       weak_prior: bool = False,
                       agreement: Callable[[FeatureResult], tuple[int, int] | None] | None = None,
                       global_candidates: int | None = None) -> FeatureResult:
    """The pose of the query whose features are `feats` (pixels of `camera`'s image): guided passes
    from the learned pose (R0, t0) when there is one; when they find no pose (or there is no prior,
    or the prior is `weak_prior`: too few of the map's cells agree with it, so the guided passes
    may have settled on a wrong pose), matching against every landmark (unless not `use_global`;
    `global_pairs` gives those matches when they are computed already); when the guided passes find
    none, SIFT + PnP's evidence too (`verified`, called only then: it is the expensive one). The
    hypothesis with the most support wins. `lm_desc` are the landmarks' `byte_products.scaled` rows. The
    answer's last pass (opts.final) is `last_pass.last_pass`'s, after this. With `agreement` (how many of the
    matches to every landmark a result explains, and how many their own pose explains; None when
    they give no pose), a guided winner that did not compete with them is checked: one that explains
    fewer than AGREEMENT of what their own pose does competes with the global hypothesis, and the
    guided hypothesis's record says what the check found. `global_candidates`: how many landmarks
    `global_pairs` compared (those of the photos retrieved for the query; None: every one)."""
    hypotheses = []
    if R0 is not None and t0 is not None:
        hypotheses.append(from_prior(landmarks, lm_desc, feats, camera, R0, t0, opts, seed))
    guided = bool(hypotheses) and hypotheses[0].success
    if use_global and (not guided or weak_prior):
        hypotheses.append(from_global(landmarks, lm_desc, feats, camera, opts, seed,
                                      global_pairs() if global_pairs is not None else None, global_candidates))
    if not guided:
        found = verified() if verified is not None else None
        if found is not None:
            hypotheses.append(from_verified(landmarks, lm_desc, feats, camera, found, opts, seed))
    best = best_hypothesis(hypotheses)
    if best.success and best.path == "guided" and use_global and agreement is not None and len(hypotheses) == 1:
        agree = agreement(best)
        if agree is not None:
            hypotheses[0].agreement = {"global_matches_explained": agree[0], "by_their_own_pose": agree[1]}
            if agree[0] < AGREEMENT * agree[1]:  # a wrong start: the matches to every landmark get their say
                hypotheses.append(from_global(landmarks, lm_desc, feats, camera, opts, seed,
                                              global_pairs() if global_pairs is not None else None, global_candidates))
            best = best_hypothesis(hypotheses)
    return best
