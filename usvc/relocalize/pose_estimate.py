"""The answer for one query photo: its pose, how it was found and how far to trust it, as the
Python API returns it and as `usvc localize` and the relocalize stage write it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from usvc.core.geometry import camera_centers, matrix_to_quat_wxyz
from usvc.core.scene import Camera


def nan_R() -> np.ndarray:
    return np.full((3, 3), np.nan)


def nan_t() -> np.ndarray:
    return np.full(3, np.nan)


@dataclass
class PoseEstimate:
    """World-to-camera pose (OpenCV axes, scene units); R and t are NaN when `success` is False.

    `inliers` is the dense RANSAC inlier count of the returned pose; `initial_R`/`initial_t` are
    the dense RANSAC pose before refinement (equal to R, t when refinement did not replace it).
    `camera` is the camera of the photo as given: the one passed in, or, when the intrinsics were
    unknown, a SIMPLE_PINHOLE with the focal length estimated with the pose.
    """

    success: bool
    R: np.ndarray
    t: np.ndarray
    inliers: int
    cells: int
    seconds: dict[str, float] = field(default_factory=dict)
    initial_R: np.ndarray = field(default_factory=nan_R)
    initial_t: np.ndarray = field(default_factory=nan_t)
    refine_iterations: int = 0
    refine_kept: bool = False
    camera: Camera | None = None
    focal_estimated: bool = False
    rejected: str = ""  # why a pose RANSAC found is not trusted (low confidence, or intrinsics the map contradicts)
    refine_method: str = "none"  # the refinement that ran: features | keypoints | none
    refine_path: str = ""  # which evidence gave the answer: guided | global | verified (features), keypoints, dense
    feature_inliers: int = 0  # PnP inliers of the feature pose (refine=features), 0 when it found none
    feature_passes: list = field(default_factory=list)  # per matching pass: kind, radius_px, candidates, matches, inliers
    feature_hypotheses: list = field(default_factory=list)  # per hypothesis tried: path, inliers after tightening
    verified: dict | None = None  # SIFT + PnP's matching, when it ran: images, pairs, correspondences, seconds
    prior: str = "learned"  # relocalize.prior: learned | none
    warnings: list = field(default_factory=list)  # doubts about the input that did not stop it (principal point...)
    pose_found: bool = True  # False when no pose was found at all (confidence 0 whatever `rejected` says)

    @property
    def confidence(self) -> float:
        """Fraction of the image's cells that agree with the pose RANSAC found (0 when it found none)."""
        return self.inliers / self.cells if (self.success or self.rejected) and self.pose_found and self.cells \
            else 0.0

    @property
    def center(self) -> np.ndarray:
        return camera_centers(self.R, self.t)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"success": self.success, "inliers": self.inliers, "cells": self.cells,
                               "confidence": round(self.confidence, 4),
                               "seconds": {k: round(v, 4) for k, v in self.seconds.items()}}
        if self.success:
            out["q_wxyz"] = [float(v) for v in matrix_to_quat_wxyz(self.R)]
            out["t"] = [float(v) for v in self.t]
            out["camera_center"] = [float(v) for v in self.center]
            out["refinement"] = {"method": self.refine_method, "path": self.refine_path,
                                 "iterations": int(self.refine_iterations), "kept": bool(self.refine_kept),
                                 "feature_inliers": int(self.feature_inliers),
                                 "learned_pose_kept": self.refine_path in ("dense", "keypoints"),
                                 "initial_q_wxyz": [float(v) for v in matrix_to_quat_wxyz(self.initial_R)]
                                 if np.isfinite(self.initial_R).all() else None,
                                 "initial_t": [float(v) for v in self.initial_t] if np.isfinite(self.initial_t).all()
                                 else None,
                                 "passes": self.feature_passes, "hypotheses": self.feature_hypotheses,
                                 "prior": self.prior}
            if self.verified is not None:
                out["refinement"]["verified_matching"] = self.verified
        elif self.feature_passes:  # refused or not found: the evidence that was weighed
            out["evidence"] = {"passes": self.feature_passes, "hypotheses": self.feature_hypotheses,
                               "prior": self.prior}
            if self.verified is not None:
                out["evidence"]["verified_matching"] = self.verified
        if self.rejected:
            out["rejected"] = self.rejected
        if self.warnings:
            out["warnings"] = list(self.warnings)
        if self.camera is not None:
            c = self.camera
            out["camera"] = {"model": c.model, "width": c.width, "height": c.height,
                             "params": [float(v) for v in c.params], "focal_estimated": self.focal_estimated}
        return out
