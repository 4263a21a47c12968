"""Keypoint-guided iterative pose refinement at query time (paper §3.2.2).

Dense RANSAC-PnP uses every cell, and cells on texture-poor or ambiguous surfaces pull the pose
off. The map's kept 3D keypoints were trained with multi-view constraints, so the cells around
where they project are the most reliable: project them with the current pose, re-solve PnP on
only those cells, and repeat while the pose still moves. A refined pose that explains fewer
cells than the dense one is not trusted, and the dense pose is kept instead.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from usvc.core.errors import UsvcError
from usvc.core.options import check
from usvc.core.scene import Camera
from usvc.relocalize.options import refine_problems
from usvc.relocalize.pnp import project_points, reprojection_inliers, solve_pnp

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineOptions:
    """Refinement parameters, from the `refine_*` fields of RelocalizeOptions (no defaults of their
    own; `relocalizer.refine_options` builds them), checked by the same rule (`refine_problems`)."""

    radius_px: float  # cells within this distance (working-image px) of a projected keypoint are used
    max_iterations: int  # T_max: at most this many PnP re-solves
    delta: float  # stop once |R_new - R_old|_F + |t_new - t_old| / median_depth is below this
    min_correspondences: int  # fewer masked cells than this (and never < 4): stop

    def problems(self) -> list[str]:
        return refine_problems(self)

    def __post_init__(self) -> None:
        check(self, "refinement")


@dataclass
class RefineResult:
    """The pose refinement returns, the dense pose it started from, and what happened on the way.

    `R`, `t` and `initial_R`, `initial_t` are world-to-camera (x_cam = R x_world + t).
    """

    R: np.ndarray  # the returned world-to-camera pose: refined if `kept`, else the initial one
    t: np.ndarray
    initial_R: np.ndarray
    initial_t: np.ndarray
    iterations: int  # accepted PnP re-solves
    kept: bool  # whether the refined pose replaced the initial one
    initial_inliers: int  # dense inliers (all cells) of the initial pose
    final_inliers: int  # dense inliers of the last refined pose (= initial_inliers without iterations)
    masked: int  # masked correspondences at the last iteration

    @property
    def inliers(self) -> int:
        """Dense inlier count of the returned pose."""
        return self.final_inliers if self.kept else self.initial_inliers


def keypoint_cell_mask(
    pixels: np.ndarray, camera: Camera, keypoints_xyz: np.ndarray, R: np.ndarray, t: np.ndarray,
    radius_px: float,
) -> np.ndarray:
    """(N,) bool: cells whose centre `pixels` (COLMAP convention) lie within radius_px of a keypoint.

    Only keypoints in front of the camera and inside the image count: the others say nothing
    about which of this image's cells are reliable.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros(len(pixels), dtype=bool)
    uv, depth = project_points(camera, keypoints_xyz, R, t)
    visible = (depth > 0) & np.all(np.isfinite(uv), axis=1)
    visible &= (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    if not visible.any() or len(pixels) == 0:
        return mask
    dist, _ = cKDTree(uv[visible]).query(pixels, k=1, distance_upper_bound=np.nextafter(radius_px, np.inf))
    return np.isfinite(dist)


def pose_change(R_old: np.ndarray, t_old: np.ndarray, R_new: np.ndarray, t_new: np.ndarray,
                median_depth: float) -> float:
    """|R_new - R_old|_F + |t_new - t_old| / median_depth: a scale-free size of one update."""
    return float(np.linalg.norm(R_new - R_old) + np.linalg.norm(t_new - t_old) / median_depth)


def refine_pose(
    pixels: np.ndarray,
    coords: np.ndarray,
    camera: Camera,
    keypoints_xyz: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    *,
    max_error_px: float,
    options: RefineOptions,
    median_depth: float | None = None,
    backend: str = "opencv",
    seed: int = 0,
    min_inliers: int = 10,
) -> RefineResult:
    """Refine the dense RANSAC pose (R0, t0) on the cells around the projected map keypoints.

    `pixels` (N,2, COLMAP convention) and `coords` (N,3) are every cell's centre and predicted
    scene coordinate; PnP uses the dense solve's backend, threshold, seed and minimum inlier
    count so the only difference is which cells it sees. `median_depth` (scene units) makes the
    convergence test scale-free; None or invalid falls back to 1.0.
    """
    opts = options
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    R0 = np.asarray(R0, dtype=np.float64)
    t0 = np.asarray(t0, dtype=np.float64).reshape(3)
    if len(pixels) != len(coords):
        raise UsvcError(f"refine_pose: {len(pixels)} pixels but {len(coords)} scene coordinates")
    if R0.shape != (3, 3) or not (np.all(np.isfinite(R0)) and np.all(np.isfinite(t0))):
        raise UsvcError("refine_pose needs a finite initial pose (R0 3x3, t0 3)")
    keypoints = np.asarray(keypoints_xyz, dtype=np.float64).reshape(-1, 3)
    scale = float(median_depth) if median_depth is not None and math.isfinite(median_depth) and median_depth > 0 \
        else 1.0
    usable = np.all(np.isfinite(coords), axis=1)

    R, t = R0, t0
    iterations = masked = 0
    for _ in range(opts.max_iterations):
        mask = keypoint_cell_mask(pixels, camera, keypoints, R, t, opts.radius_px) & usable
        masked = int(mask.sum())
        if masked < max(opts.min_correspondences, 4):  # PnP needs 4 whatever the setting
            log.debug("refinement: %d masked cells < %d, stopping", masked, opts.min_correspondences)
            break
        res = solve_pnp(pixels[mask], coords[mask], camera, max_error_px=max_error_px, seed=seed,
                        min_inliers=min_inliers, backend=backend)
        if not res.success:
            log.debug("refinement: PnP on %d masked cells failed, stopping", masked)
            break
        change = pose_change(R, t, res.R, res.t, scale)
        R, t = res.R, res.t
        iterations += 1
        if change < opts.delta:
            break

    initial_inliers = int(reprojection_inliers(camera, pixels, coords, R0, t0, max_error_px).sum())
    final_inliers = initial_inliers if iterations == 0 else \
        int(reprojection_inliers(camera, pixels, coords, R, t, max_error_px).sum())
    kept = iterations > 0 and final_inliers >= initial_inliers
    log.debug("refinement: %d iterations, dense inliers %d -> %d, %s", iterations, initial_inliers,
              final_inliers, "kept" if kept else "initial pose kept")
    R_out, t_out = (R, t) if kept else (R0, t0)
    return RefineResult(R_out.copy(), t_out.copy(), R0.copy(), t0.copy(), iterations, kept, initial_inliers,
                        final_inliers, masked)
