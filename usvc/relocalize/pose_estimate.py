"""The answer for one query photo: its pose, how it was found and how far to trust it, as the
Python API returns it and as `usvc localize` and the relocalize stage write it (`PoseEstimate`);
and the query that it is made of, as the relocalizer's steps fill it in (`Query`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from usvc.core.geometry import camera_centers, matrix_to_quat_wxyz
from usvc.core.scene import Camera
from usvc.relocalize.answer_checks import far_camera_verdict, no_pose_reason
from usvc.relocalize.options import RelocalizeOptions

if TYPE_CHECKING:
    from usvc.relocalize.features.path import FeatureResult
    from usvc.relocalize.pnp import PnPResult
    from usvc.relocalize.query_cores import Job

FEATURE_PATHS = ("guided", "global", "verified")  # answers that came from the photo's features


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


@dataclass
class Query:
    """One photo's query as `Relocalizer._localize`'s steps fill it in: the photo (`_photo`), the
    map's coordinates of its cells (`_coordinates`), the learned pose (`_learned_pose`) and the
    answer as refinement and the verdicts leave it; the PoseEstimate is made of it (`estimate`)."""

    t0: float  # perf_counter when the query started
    width: int  # the photo's size
    height: int
    intrinsics: bool  # whether they were given (else the focal length is estimated with the pose)
    source: str  # where they came from, for the reasons a query they fail gives
    given: Camera | None  # the camera the answer reports: the given one, else the one estimated with the pose
    warnings: list[str]
    gray: np.ndarray  # the network's grey: undistorted, at the map's working size
    resize: float  # the working size over the photo's
    camera: Camera | None  # gray's camera, None while the focal length is unknown
    full_camera: Camera | None  # the undistorted photo's, at its own size: what the features see
    sift_job: Job | None  # the photo's SIFT, found beside the network (refine=features)
    t1: float = 0.0  # perf_counter before the network, after it, after the dense PnP
    t2: float = 0.0
    t3: float = 0.0
    coords: np.ndarray | None = None  # (h, w, 3) scene coordinates of gray's 8x8 cells
    pixels: np.ndarray | None = None  # (cells, 2) their centres
    cells: int = 0
    threshold: float = 0.0  # the dense PnP's inlier threshold, px at the working size
    no_focal: str = ""  # why the map's coordinates gave no focal length, when the photo has none
    map_focal: Callable[[], Camera | None] | None = None  # the map's own focal estimate, for its verdicts
    dense: PnPResult | None = None  # the learned pose
    # the answer, as refinement and the verdicts leave it
    R: np.ndarray = field(default_factory=nan_R)
    t: np.ndarray = field(default_factory=nan_t)
    inliers: int = 0  # the cells that agree with (R, t)
    iterations: int = 0  # keypoint-guided refinement's
    kept: bool = False
    path: str = "dense"  # which evidence the pose came from: FEATURE_PATHS, keypoints or dense
    feature: FeatureResult | None = None  # what refinement by features found
    rejected: str = ""

    def estimate(self, extent: Callable[[], tuple[np.ndarray, float] | None], options: RelocalizeOptions,
                 refine_method: str) -> PoseEstimate:
        """The answer: the pose where the evidence and every verdict let it stand (the last, a camera far
        outside the map's `extent`: `far_camera_verdict`), else NaN and why not."""
        assert self.dense is not None
        t4 = time.perf_counter()
        seconds = {"preprocess": self.t1 - self.t0, "network": self.t2 - self.t1, "pnp": self.t3 - self.t2,
                   "refine": t4 - self.t3, "total": t4 - self.t0}
        feature, dense = self.feature, self.dense
        if feature is not None and feature.verified_seconds is not None:  # SIFT + PnP's matching, part of refine
            seconds["fallback"] = feature.verified_seconds
        by_features = self.path in FEATURE_PATHS
        R, t, rejected = self.R, self.t, self.rejected
        if (dense.success or by_features) and not rejected:
            rejected = far_camera_verdict(camera_centers(R, t), extent())
        success = (dense.success or by_features) and not rejected
        pose_found = bool(dense.success or (feature is not None and feature.success))
        if not success:
            R, t = nan_R(), nan_t()
            if not rejected:  # every failure says why
                rejected = self.no_focal or no_pose_reason(options.min_inliers, dense.num_inliers, self.cells,
                                                           None if feature is None else feature.why)
        return PoseEstimate(success, R, t, self.inliers, self.cells, seconds,
                            initial_R=dense.R.copy() if success and dense.success else nan_R(),
                            initial_t=dense.t.copy() if success and dense.success else nan_t(),
                            refine_iterations=self.iterations, refine_kept=self.kept or by_features,
                            camera=self.given, focal_estimated=not self.intrinsics, rejected=rejected,
                            refine_method=refine_method, refine_path=self.path if success else "",
                            feature_inliers=feature.inliers if feature is not None else 0,
                            feature_passes=feature.passes if feature is not None else [],
                            feature_hypotheses=feature.tried if feature is not None else [],
                            verified=feature.verified if feature is not None else None,
                            warnings=self.warnings, pose_found=pose_found, prior=options.prior)
