"""Query-time evaluation: pose error metrics, the poses.txt format and RANSAC-PnP."""

from usvc.evaluation.pnp import BACKENDS, PnPResult, project_points, reprojection_inliers, solve_pnp
from usvc.evaluation.pose_errors import (
    read_poses_txt,
    rotation_error_deg,
    summarize,
    translation_error,
    write_poses_txt,
)

__all__ = [
    "BACKENDS",
    "PnPResult",
    "project_points",
    "read_poses_txt",
    "reprojection_inliers",
    "rotation_error_deg",
    "solve_pnp",
    "summarize",
    "translation_error",
    "write_poses_txt",
]
