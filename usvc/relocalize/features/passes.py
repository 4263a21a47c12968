"""The passes of refinement by features: LO-RANSAC PnP on the query's SIFT keypoints matched to the
SfM model's own landmarks gives the exact pose.

Guided pass (`from_prior`): the landmarks a pose sees (in front, inside the image, and looked at
from within the cone of directions they were mapped from) are projected; each is compared only
with query keypoints within a radius of its projection (`matching.guided_matches`), and LO-RANSAC
PnP with non-linear refinement re-estimates the pose. The radius then shrinks and the pass repeats
from the new pose. Unguided correspondences give a pose the same guided passes then tighten: the
query's keypoints matched against every landmark (`from_global`), and SIFT + PnP's own evidence
(`from_verified`: `verified_matching`, every mapping image's observed keypoints, verified per
pair, lifted through the tracks; not tightened). Which of them run, and which answer wins, is
`path.refine_by_features`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from usvc.core.geometry import camera_centers
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.features.matching import global_matches, guided_matches
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import VerifiedMatches
from usvc.relocalize.options import REFERENCE_SHORT_SIDE, RelocalizeOptions
from usvc.relocalize.pnp import in_image, project_points, solve_pnp

# SIFT + PnP's inlier threshold for a query's pose, px at the mapping images' size: the value with
# which `benchmarks.accuracy baseline-sift` registers queries (usvc.sfm.posing.QUERY_MAX_ERROR_PX; a test
# keeps the two equal without the query step importing the SfM step)
VERIFIED_MAX_ERROR_PX = 4.0
# The fewest LO-RANSAC trials of a feature PnP (COLMAP's default floor: 100). Guided matches are
# nearly all inliers (mini's ~1,000 a pass: 99 %), where RANSAC's adaptive stop needs a handful of
# trials and the floor made every pass run 100, each scored on every match: 20 took ~4 ms off each
# PnP (of ~13) with the same poses (docs/speed.md). Where inliers are few the adaptive count rules.
FEATURE_MIN_TRIALS = 20


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
    final_comparisons: int = 0  # the last pass's descriptor comparisons at most (0: no bound)


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
                               final_images=options.features_final_images,
                               final_comparisons=options.features_final_comparisons)


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
