"""RANSAC-PnP from dense 2D–3D correspondences (scene coordinate predictions).

Interchangeable backends so their accuracy and speed can be compared on the same inputs:
"pycolmap" (COLMAP's LO-RANSAC with P3P, then non-linear refinement), "poselib" (PoseLib's
LO-RANSAC with P3P and its own Levenberg–Marquardt refinement on the inliers, Cauchy loss of 1 px
as COLMAP's) and "opencv" (USAC with P3P, then Levenberg–Marquardt on the inliers, re-selecting
inliers until the set stops growing, as ACE does). All take pixel coordinates in COLMAP's
convention (top-left pixel centre at (0.5, 0.5)) and return world-to-camera (R, t) in OpenCV axes.

"opencv" is the default: on `python -m benchmarks.accuracy pnp-solvers` (4800 correspondences at 640x480,
30-95 % outliers) it was as accurate or slightly more accurate at every outlier ratio and
2-20x faster than pycolmap's LO-RANSAC. Refinement by features' passes, whose matches are nearly
all inliers, take "poselib" (`relocalize.features_pnp`): about half COLMAP's time there.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np
import poselib
import pycolmap

from usvc.core.absolute_pose import RANSAC_CONFIDENCE, RANSAC_MAX_TRIALS, absolute_pose_options
from usvc.core.errors import UsvcError
from usvc.core.scene import Camera
from usvc.relocalize.counted_refinement import refine_weighted
from usvc.relocalize.options import BACKENDS

log = logging.getLogger(__name__)

_REFINE_ROUNDS = 10


@dataclass
class PnPResult:
    """A solved (or failed) pose; on failure R and t are NaN so they cannot be used by mistake.

    `R`, `t` are world-to-camera (x_cam = R x_world + t, OpenCV axes).
    """

    success: bool
    R: np.ndarray
    t: np.ndarray
    inlier_mask: np.ndarray
    num_inliers: int
    seconds: float


def _opencv_intrinsics(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """K and distCoeffs in OpenCV's convention; every COLMAP model we support maps exactly.

    OpenCV puts pixel centres on integers, so the principal point moves by −0.5 along with the
    image points: the projection is unchanged, only the origin of the pixel grid differs.
    """
    K = camera.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    p = camera.params
    if camera.model in ("SIMPLE_PINHOLE", "PINHOLE"):
        dist = np.zeros(4)
    elif camera.model == "SIMPLE_RADIAL":
        dist = np.array([p[3], 0.0, 0.0, 0.0])
    elif camera.model == "RADIAL":
        dist = np.array([p[3], p[4], 0.0, 0.0])
    elif camera.model == "OPENCV":
        dist = np.array(p[4:8], dtype=np.float64)
    else:
        raise UsvcError(f"opencv PnP backend does not support camera model {camera.model}")
    return K, dist


def _reprojection_inliers(
    p3: np.ndarray, p2_cv: np.ndarray, K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
    max_error_px: float,
) -> np.ndarray:
    """Points in front of the camera that reproject within max_error_px."""
    R, _ = cv2.Rodrigues(rvec)
    depth = p3 @ R[2] + tvec.reshape(3)[2]
    proj, _ = cv2.projectPoints(p3, rvec, tvec, K, dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - p2_cv, axis=1)
    return (depth > 0) & (err < max_error_px)


def project_points(
    camera: Camera, points3d: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) COLMAP-convention pixels and (N,) camera depths of world points under (R, t).

    Public so refinement and inlier counting project exactly as the solver's inlier test does
    (same intrinsics and distortion); pixels of points behind the camera are meaningless.
    """
    p3 = np.ascontiguousarray(np.asarray(points3d, dtype=np.float64).reshape(-1, 3))
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    if len(p3) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    if camera.model in ("SIMPLE_PINHOLE", "PINHOLE"):  # no distortion: the pinhole's arithmetic in numpy, about
        cam = p3 @ R.T + t  # a tenth of projectPoints' time on a map's landmarks (the same pixels to ~1e-13)
        (fx, fy), (cx, cy) = camera.focal, camera.principal_point
        with np.errstate(divide="ignore", invalid="ignore"):  # a point at depth 0 has no pixel (inf/nan)
            return np.stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy], axis=1), cam[:, 2]
    K, dist = _opencv_intrinsics(camera)
    rvec, _ = cv2.Rodrigues(R)
    proj, _ = cv2.projectPoints(p3, rvec, t, K, dist)
    return proj.reshape(-1, 2) + 0.5, p3 @ R[2] + t[2]


def reprojection_inliers(
    camera: Camera, points2d: np.ndarray, points3d: np.ndarray, R: np.ndarray, t: np.ndarray,
    max_error_px: float,
) -> np.ndarray:
    """(N,) bool: finite correspondences in front of the camera that reproject within max_error_px.

    The same test `solve_pnp` ("opencv") uses to pick inliers, so counts from different poses
    (e.g. before and after refinement) are comparable.
    """
    p2 = np.asarray(points2d, dtype=np.float64).reshape(-1, 2)
    p3 = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
    if len(p2) != len(p3):
        raise UsvcError(f"reprojection_inliers: {len(p2)} pixels but {len(p3)} points")
    mask = np.zeros(len(p2), dtype=bool)
    finite = np.all(np.isfinite(p2), axis=1) & np.all(np.isfinite(p3), axis=1)
    if not (finite.any() and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return mask
    K, dist = _opencv_intrinsics(camera)
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    tvec = np.asarray(t, dtype=np.float64).reshape(3, 1)
    mask[finite] = _reprojection_inliers(np.ascontiguousarray(p3[finite]), p2[finite] - 0.5, K, dist, rvec, tvec,
                                         max_error_px)
    return mask


def _solve_opencv(
    p2: np.ndarray, p3: np.ndarray, camera: Camera, max_error_px: float, seed: int, min_inliers: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    K, dist = _opencv_intrinsics(camera)
    p2_cv = np.ascontiguousarray(p2 - 0.5)
    p3 = np.ascontiguousarray(p3)
    cv2.setRNGSeed(seed)
    # USAC (uniform sampling, MSAC score, inner local optimisation) rather than the classic
    # solvePnPRansac: the classic loop samples 4 points per P3P hypothesis and ran ~40x slower
    # at 85 % outliers in `benchmarks.accuracy pnp-solvers` for the same accuracy.
    params = cv2.UsacParams()
    params.threshold = float(max_error_px)
    params.confidence = RANSAC_CONFIDENCE
    params.maxIterations = RANSAC_MAX_TRIALS
    params.randomGeneratorState = int(seed)
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MSAC
    params.loMethod = cv2.LOCAL_OPTIM_INNER_LO
    ok, _, rvec, tvec, _ = cv2.solvePnPRansac(p3, p2_cv, K.copy(), dist, params=params)
    if not ok or rvec is None or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    inliers = _reprojection_inliers(p3, p2_cv, K, dist, rvec, tvec, max_error_px)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
    for _ in range(_REFINE_ROUNDS):
        if inliers.sum() < max(min_inliers, 4):
            break
        rvec, tvec = cv2.solvePnPRefineLM(p3[inliers], p2_cv[inliers], K, dist, rvec, tvec, criteria=criteria)
        grown = _reprojection_inliers(p3, p2_cv, K, dist, rvec, tvec, max_error_px)
        stop = grown.sum() <= inliers.sum()
        inliers = grown
        if stop:
            break
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.reshape(3), inliers


def _pycolmap_camera(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=list(camera.params))


def _solve_poselib(
    p2: np.ndarray, p3: np.ndarray, camera: Camera, max_error_px: float, seed: int, min_trials: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """PoseLib's LO-RANSAC (P3P) and refinement, with COLMAP's RANSAC settings (confidence, the most
    trials, `min_trials` or COLMAP's 100 as the fewest, the seed) and its 1 px Cauchy loss. PoseLib
    takes every camera model usvc knows by COLMAP's name and parameter order (a test holds its
    projections to COLMAP's)."""
    cam = {"model": camera.model, "width": int(camera.width), "height": int(camera.height),
           "params": [float(v) for v in camera.params]}
    ransac = {"max_reproj_error": float(max_error_px), "seed": int(seed), "success_prob": RANSAC_CONFIDENCE,
              "max_iterations": RANSAC_MAX_TRIALS, "min_iterations": int(100 if min_trials is None else min_trials)}
    pose, info = poselib.estimate_absolute_pose(p2, p3, cam, ransac, {"loss_type": "CAUCHY", "loss_scale": 1.0})
    inliers = np.asarray(info.get("inliers", []), bool)
    R, t = np.asarray(pose.R, np.float64), np.asarray(pose.t, np.float64).reshape(3)
    if len(inliers) != len(p2) or inliers.sum() < 4 or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    return R, t, inliers


def in_image(camera: Camera, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(N,) bool: projections (`project_points`) in front of the camera and inside its image."""
    return (depth > 0) & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)


def _solve_pycolmap(
    p2: np.ndarray, p3: np.ndarray, camera: Camera, max_error_px: float, seed: int, min_trials: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    cam = _pycolmap_camera(camera)
    est = absolute_pose_options(max_error_px, seed)
    if min_trials is not None:
        est.ransac.min_num_trials = int(min_trials)
    ref = pycolmap.AbsolutePoseRefinementOptions()
    res = pycolmap.estimate_and_refine_absolute_pose(p2, p3, cam, est, ref)
    if res is None:
        return None
    pose = res["cam_from_world"]
    return pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64), np.asarray(res["inlier_mask"], bool)


def refine_on_inliers(points2d: np.ndarray, points3d: np.ndarray, camera: Camera, R: np.ndarray, t: np.ndarray,
                      max_error_px: float, rounds: int = 2, counts: np.ndarray | None = None) -> PnPResult:
    """The pose (R, t) refined on the correspondences it explains within `max_error_px`: COLMAP's
    non-linear absolute-pose refinement (the last step of its LO-RANSAC), then the inliers again
    under the refined pose, `rounds` times. For correspondences a pose has already checked, where
    RANSAC's sampling would only find that pose again. Failure (success False) when the refinement
    does not converge or fewer than 4 correspondences are inliers.

    With `counts`, each correspondence stands for that many repetitions of itself (SIFT + PnP counts
    a match once per mapping image it was found in): the same objective over the repetitions, each
    distinct correspondence weighted by its count (`counted_refinement.refine_weighted` for an
    undistorted camera, a tenth of COLMAP's time on the repetitions; COLMAP's on the repetitions
    for a camera with distortion). The inlier mask is over the given correspondences."""
    if counts is not None and camera.has_distortion:
        rows = np.repeat(np.arange(len(counts)), np.asarray(counts, np.int64))
        res = refine_on_inliers(np.asarray(points2d)[rows], np.asarray(points3d)[rows], camera, R, t, max_error_px,
                                rounds)
        mask = np.zeros(len(counts), bool)
        mask[rows[res.inlier_mask]] = True
        return PnPResult(res.success, res.R, res.t, mask, int(mask.sum()), res.seconds)
    start = time.perf_counter()
    p2 = np.ascontiguousarray(points2d, dtype=np.float64)
    p3 = np.ascontiguousarray(points3d, dtype=np.float64)
    cam = _pycolmap_camera(camera)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    mask = reprojection_inliers(camera, p2, p3, R, t, max_error_px)
    for _ in range(rounds):
        if int(mask.sum()) < 4:
            break
        if counts is not None:
            R, t, converged = refine_weighted(p2[mask], p3[mask], np.asarray(counts)[mask], camera, R, t)
            if not converged:
                break
        else:
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
            res = pycolmap.refine_absolute_pose(pose, p2, p3, mask, cam, pycolmap.AbsolutePoseRefinementOptions())
            if res is None:
                break
            pose = res["cam_from_world"]
            R, t = pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64)
        mask = reprojection_inliers(camera, p2, p3, R, t, max_error_px)
    else:
        return PnPResult(True, R, t, mask, int(mask.sum()), time.perf_counter() - start)
    return PnPResult(False, np.full((3, 3), np.nan), np.full(3, np.nan), mask, int(mask.sum()),
                     time.perf_counter() - start)


def solve_pnp(
    points2d: np.ndarray,
    points3d: np.ndarray,
    camera: Camera,
    max_error_px: float = 10.0,
    seed: int = 0,
    min_inliers: int = 10,
    backend: str = "opencv",
    min_trials: int | None = None,
) -> PnPResult:
    """Robust world-to-camera pose from (N,2) COLMAP-convention pixels and (N,3) world points.

    `min_trials` ("pycolmap" and "poselib"; None: COLMAP's 100) is the fewest RANSAC trials before its
    adaptive stop may end the search: the stop itself (confidence RANSAC_CONFIDENCE at the inlier
    ratio found so far) still decides where inliers are few, so a lower floor only shortens the
    search on correspondences that are nearly all inliers.

    Non-finite correspondences are dropped first (their inlier flag is False). Too few inliers
    is an ordinary outcome (success False); malformed input raises UsvcError.
    """
    if backend not in BACKENDS:
        raise UsvcError(f"unknown PnP backend {backend!r}; known: {list(BACKENDS)}")
    p2 = np.asarray(points2d, dtype=np.float64)
    p3 = np.asarray(points3d, dtype=np.float64)
    if p2.ndim != 2 or p2.shape[1] != 2 or p3.ndim != 2 or p3.shape[1] != 3 or len(p2) != len(p3):
        raise UsvcError(f"PnP needs (N,2) and (N,3) correspondences, got {p2.shape} and {p3.shape}")
    if not max_error_px > 0:
        raise UsvcError(f"PnP max_error_px must be positive, got {max_error_px}")
    if seed < 0:
        raise UsvcError(f"PnP seed must be non-negative for reproducible runs, got {seed}")
    if min_trials is not None and (backend == "opencv" or not 1 <= min_trials <= RANSAC_MAX_TRIALS):
        raise UsvcError(f"PnP min_trials={min_trials!r}: only the pycolmap and poselib backends take it, "
                        f"between 1 and {RANSAC_MAX_TRIALS}")
    finite = np.all(np.isfinite(p2), axis=1) & np.all(np.isfinite(p3), axis=1)
    n_finite = int(finite.sum())
    if n_finite < 4:
        raise UsvcError(f"PnP needs at least 4 finite correspondences, got {n_finite} of {len(p2)}")

    start = time.perf_counter()
    if backend == "pycolmap":
        out = _solve_pycolmap(np.ascontiguousarray(p2[finite]), np.ascontiguousarray(p3[finite]), camera,
                              max_error_px, seed, min_trials)
    elif backend == "poselib":
        out = _solve_poselib(np.ascontiguousarray(p2[finite]), np.ascontiguousarray(p3[finite]), camera,
                             max_error_px, seed, min_trials)
    else:
        out = _solve_opencv(p2[finite], p3[finite], camera, max_error_px, seed, min_inliers)
    seconds = time.perf_counter() - start

    mask = np.zeros(len(p2), dtype=bool)
    nan_R, nan_t = np.full((3, 3), np.nan), np.full(3, np.nan)
    if out is None:
        log.debug("PnP (%s) found no pose from %d correspondences", backend, n_finite)
        return PnPResult(False, nan_R, nan_t, mask, 0, seconds)
    R, t, inliers = out
    mask[finite] = inliers
    num = int(mask.sum())
    if num < min_inliers:
        log.debug("PnP (%s): %d inliers < %d required", backend, num, min_inliers)
        return PnPResult(False, nan_R, nan_t, mask, num, seconds)
    return PnPResult(True, R, t, mask, num, seconds)
