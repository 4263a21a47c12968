"""A pose refined on correspondences that repeat: SIFT + PnP's evidence counts a query keypoint once
per mapping image it matched in, so the same (keypoint, landmark) pair is often there 5-15 times
(mini: ~10,900 correspondences, ~700 distinct pairs). Each repetition is the same residual, so
the robust cost over all of them equals the cost over the distinct pairs, each weighted by its
count. COLMAP's refinement (`pycolmap.refine_absolute_pose`: Cauchy loss of scale 1 px on the
reprojection error, Levenberg-Marquardt) has no weights in its Python API, so it had to be given
every repetition: ~21 ms a call on mini's. `refine_weighted` minimises the same objective,
sum over pairs of count x Cauchy(squared reprojection error), by Levenberg-Marquardt on the
distinct pairs (a few ms), for undistorted (pinhole) cameras; `pnp.refine_on_inliers(counts=...)`
uses it (COLMAP's on the repetitions for a camera with distortion). A test holds the two to the
same pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from usvc.core.scene import Camera

LOSS_SCALE_PX = 1.0  # COLMAP's AbsolutePoseRefinementOptions.loss_function_scale
MAX_ITERATIONS = 100  # COLMAP's max_num_iterations
_STEP_TOLERANCE = 1e-12  # stop when no parameter moves more than this (radians, scene units)
_COST_TOLERANCE = 1e-12  # ... or the cost falls by less than this share of it
_MAX_DAMPING = 1e8  # give up improving when even this damping gives no lower cost


def distinct_pairs(keypoint: np.ndarray, landmark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row of each distinct (keypoint, landmark) pair's first occurrence, in order; how often it occurs)."""
    key = np.asarray(keypoint, np.int64) * (int(np.max(landmark, initial=0)) + 1) + np.asarray(landmark, np.int64)
    _, first, counts = np.unique(key, return_index=True, return_counts=True)
    order = np.argsort(first)
    return first[order], counts[order]


def _cost(err2: np.ndarray, weight: np.ndarray, a2: float) -> float:
    return float(np.sum(weight * a2 * np.log1p(err2 / a2)))


def _residuals(uv: np.ndarray, xyz: np.ndarray, R: np.ndarray, t: np.ndarray, f: np.ndarray,
               c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = xyz @ R.T + t
    return cam[:, :2] / cam[:, 2:3] * f + c - uv, cam


def refine_weighted(uv: np.ndarray, xyz: np.ndarray, weight: np.ndarray, camera: Camera, R: np.ndarray,
                    t: np.ndarray, loss_scale: float = LOSS_SCALE_PX) -> tuple[np.ndarray, np.ndarray, bool]:
    """(R, t, converged): the world-to-camera pose minimising sum_i weight_i x Cauchy(|e_i|^2) over
    the reprojection errors e_i (px, COLMAP's pixel convention) of an undistorted camera, by
    Levenberg-Marquardt from (R, t) (rotation updated on the left, as R <- exp(w) R, t <- exp(w) t + v).
    Not converged: a non-finite step or cost; the pose is then the start."""
    if camera.has_distortion:
        raise ValueError(f"refine_weighted takes an undistorted camera, not {camera.model}")
    f, c = np.asarray(camera.focal, np.float64), np.asarray(camera.principal_point, np.float64)
    uv, xyz = np.asarray(uv, np.float64), np.asarray(xyz, np.float64)
    weight = np.asarray(weight, np.float64)
    R0, t0 = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    R, t = R0, t0
    a2 = float(loss_scale) ** 2
    err, cam = _residuals(uv, xyz, R, t, f, c)
    cost = _cost((err ** 2).sum(1), weight, a2)
    if not np.isfinite(cost):
        return R0, t0, False
    damping = 1e-6
    for _ in range(MAX_ITERATIONS):
        w = weight / (1.0 + (err ** 2).sum(1) / a2)  # the Cauchy loss's derivative: IRLS weights
        iz = 1.0 / cam[:, 2]
        zero = np.zeros_like(iz)
        du = np.stack([f[0] * iz, zero, -f[0] * cam[:, 0] * iz * iz], 1)  # d(u, v) / d(camera point)
        dv = np.stack([zero, f[1] * iz, -f[1] * cam[:, 1] * iz * iz], 1)
        ju = np.concatenate([np.cross(cam, du), du], 1)  # d(u, v) / d(w, v): w x X moves the point
        jv = np.concatenate([np.cross(cam, dv), dv], 1)
        H = (ju * w[:, None]).T @ ju + (jv * w[:, None]).T @ jv
        g = ju.T @ (w * err[:, 0]) + jv.T @ (w * err[:, 1])
        while True:
            try:
                step = -np.linalg.solve(H + damping * np.diag(np.diag(H)), g)
            except np.linalg.LinAlgError:
                return R0, t0, False
            if not np.all(np.isfinite(step)):
                return R0, t0, False
            turn = Rotation.from_rotvec(step[:3]).as_matrix()
            R_new, t_new = turn @ R, turn @ t + step[3:]
            err_new, cam_new = _residuals(uv, xyz, R_new, t_new, f, c)
            cost_new = _cost((err_new ** 2).sum(1), weight, a2)
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            damping *= 10.0
            if damping > _MAX_DAMPING:
                return R, t, True  # no step lowers the cost: a minimum
        fell = cost - cost_new
        R, t, err, cam, cost = R_new, t_new, err_new, cam_new, cost_new
        damping = max(damping / 10.0, 1e-12)
        if np.abs(step).max() < _STEP_TOLERANCE or fell <= _COST_TOLERANCE * max(cost, 1e-300):
            break
    return R, t, True
