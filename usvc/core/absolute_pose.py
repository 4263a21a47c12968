"""Absolute pose with pycolmap's LO-RANSAC: its settings, and the focal length of an uncalibrated
photo estimated with its pose (P4Pf). Shared by the relocalizer (usvc.relocalize.pnp) and by
training, which measures how well a map's coordinates tell its own views' focal lengths."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from usvc.core.scene import Camera

RANSAC_CONFIDENCE = 0.99999
RANSAC_MAX_TRIALS = 10000
# COLMAP caps its trial count by the inlier ratio it assumes at worst; dense SCR output can sit
# well below COLMAP's default of 0.1, so assume less rather than give up early.
RANSAC_MIN_INLIER_RATIO = 0.02


def absolute_pose_options(max_error_px: float, seed: int) -> pycolmap.AbsolutePoseEstimationOptions:
    """pycolmap's RANSAC settings shared by the pose and the pose-with-focal solvers."""
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = max_error_px
    est.ransac.random_seed = seed
    est.ransac.confidence = RANSAC_CONFIDENCE
    est.ransac.max_num_trials = RANSAC_MAX_TRIALS
    est.ransac.min_inlier_ratio = RANSAC_MIN_INLIER_RATIO
    return est


@dataclass
class FocalPose:
    """A focal length estimated with the pose (P4Pf): the camera, the pose and its inliers.

    `R`, `t` are world-to-camera (pycolmap's cam_from_world: x_cam = R x_world + t).
    """

    camera: Camera
    R: np.ndarray
    t: np.ndarray
    inlier_mask: np.ndarray


def estimate_focal_pose(
    points2d: np.ndarray, points3d: np.ndarray, width: int, height: int, max_error_px: float, seed: int = 0,
) -> FocalPose | None:
    """The focal length of an uncalibrated photo with its pose (pycolmap's P4Pf LO-RANSAC, then
    refinement of pose and focal); principal point at the image centre. None when no pose
    explains enough correspondences (or fewer than 8 finite ones are given)."""
    p2 = np.asarray(points2d, dtype=np.float64).reshape(-1, 2)
    p3 = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(p2), axis=1) & np.all(np.isfinite(p3), axis=1)
    if finite.sum() < 8:
        return None
    # COLMAP's prior for a camera without calibration: 1.2 x the longer side.
    cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=width, height=height,
                          params=[1.2 * max(width, height), width / 2, height / 2])
    est = absolute_pose_options(max_error_px, seed)
    est.estimate_focal_length = True
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.refine_focal_length = True
    res = pycolmap.estimate_and_refine_absolute_pose(np.ascontiguousarray(p2[finite]), np.ascontiguousarray(p3[finite]),
                                                     cam, est, ref)
    f = float(cam.params[0])  # refined in place
    if res is None or not (np.isfinite(f) and f > 0):
        return None
    mask = np.zeros(len(p2), dtype=bool)
    mask[np.flatnonzero(finite)] = np.asarray(res["inlier_mask"], bool).reshape(-1)
    pose = res["cam_from_world"]
    return FocalPose(Camera("SIMPLE_PINHOLE", width, height, (f, width / 2, height / 2)), pose.rotation.matrix(),
                     np.asarray(pose.translation, dtype=np.float64), mask)


def estimate_focal(
    points2d: np.ndarray, points3d: np.ndarray, width: int, height: int, max_error_px: float, seed: int = 0,
) -> Camera | None:
    """The focal length of an uncalibrated photo, estimated with its pose (`estimate_focal_pose`):
    a SIMPLE_PINHOLE camera, or None when no pose explains enough correspondences."""
    found = estimate_focal_pose(points2d, points3d, width, height, max_error_px, seed)
    return None if found is None else found.camera


def focal_log_std(found: FocalPose, points2d: np.ndarray, points3d: np.ndarray) -> float:
    """The standard deviation of ln(focal length) that `found`'s inliers allow: the Gauss-Newton
    covariance sigma^2 (J^T J)^-1 of (rotation, translation, ln f) at the refined pose, with sigma^2
    the inliers' residual variance. A deep view pins the focal length to a fraction of a per cent;
    a shallow one leaves it free (a focal length off is then a camera moved along its axis). inf
    when the inliers cannot tell it at all (too few, or a singular system)."""
    mask = np.asarray(found.inlier_mask, bool)
    p2 = np.asarray(points2d, np.float64).reshape(-1, 2)[mask]
    p3 = np.asarray(points3d, np.float64).reshape(-1, 3)[mask]
    f, cx, cy = found.camera.params
    Y = p3 @ np.asarray(found.R, np.float64).T + np.asarray(found.t, np.float64)
    n = len(Y)
    if n < 8 or np.any(Y[:, 2] <= 0):
        return float("inf")
    z = Y[:, 2]
    x, y = Y[:, 0] / z, Y[:, 1] / z
    residual = np.concatenate([f * x + cx - p2[:, 0], f * y + cy - p2[:, 1]])
    du = f * np.stack([1.0 / z, np.zeros(n), -x / z], 1)  # d(u, v) / d(camera coordinates)
    dv = f * np.stack([np.zeros(n), 1.0 / z, -y / z], 1)
    # a rotation increment w moves camera coordinates by w x Y; ln f scales (u - cx, v - cy)
    J = np.concatenate([np.concatenate([np.cross(Y, d), d, (f * c)[:, None]], 1) for d, c in ((du, x), (dv, y))])
    sigma2 = float(residual @ residual) / max(2 * n - 7, 1)
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(cov[6, 6])) if np.isfinite(cov[6, 6]) and cov[6, 6] >= 0 else float("inf")
