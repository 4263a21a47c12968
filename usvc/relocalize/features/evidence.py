"""A query photo's correspondences to the landmarks that do not depend on its intrinsics, computed
once per query and only when asked for: the matches to every landmark's one descriptor (cheap),
then SIFT + PnP's verified matches (`verified_matching`: the expensive fallback). The relocalizer's
hypotheses and its focal-length checks (P4Pf) share them, and the P4Pf on the matches to every
landmark also tells whether a guided answer agrees with them (`QueryEvidence.agreement`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from usvc.core.absolute_pose import FocalPose, estimate_focal_pose
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.features.byte_products import ByteRows
from usvc.relocalize.features.matching import global_matches
from usvc.relocalize.features.passes import FeatureMatchOptions
from usvc.relocalize.features.retrieval import Retrieved
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import HeldKeypointDescriptors, VerifiedMatches, verified_matches
from usvc.relocalize.pnp import reprojection_inliers


class QueryEvidence:
    """`camera` is the query's at the feature image's size (an assumed focal length is fine: the
    verification tells an essential from a fundamental matrix); `use_global` False (prior=none)
    leaves the global matches out of `unguided`; `global_pairs` gives those matches when they are
    being found already (on the worker thread: `usvc.relocalize.query_cores.Job`); SIFT + PnP's
    pairs are verified on `opts.threads`."""

    def __init__(self, landmarks: Landmarks, landmark_desc: np.ndarray, observation_desc: list[ByteRows] | None,
                 feats: QueryFeatures, opts: FeatureMatchOptions, camera: Camera, seed: int,
                 use_global: bool = True,
                 global_pairs: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
                 landmark_bytes: ByteRows | None = None,
                 keypoint_desc: HeldKeypointDescriptors | None = None, focal_known: bool = True,
                 retrieved: Retrieved = Retrieved()) -> None:
        self.landmarks, self.landmark_desc, self.observation_desc = landmarks, landmark_desc, observation_desc
        self.keypoint_desc = keypoint_desc  # the mapping keypoints' descriptors, held once per map
        self.focal_known = focal_known  # the photo's focal length was given (SIFT + PnP's pairs then verify calibrated)
        self.landmark_bytes = landmark_bytes  # the landmarks' bytes for the global matches' int8 products
        self.feats, self.opts, self.camera, self.seed = feats, opts, camera, seed
        self.retrieved = retrieved  # the mapping photos (and their landmarks) the query is matched against
        self.use_global = use_global or landmarks.observations is None
        self._global: tuple[np.ndarray, np.ndarray] | None = None
        self._global_source = global_pairs
        self.focal_estimated = False  # whether P4Pf on these correspondences gave the photo's focal length
        self._verified: VerifiedMatches | None = None
        self._global_focal: tuple[FocalPose | None] | None = None

    def global_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(landmark rows, keypoint rows) of the matches to every landmark (those of the retrieved photos)."""
        if self._global is None:
            self._global = self._global_source() if self._global_source is not None \
                else global_matches(self.landmark_desc, self.feats, self.opts.ratio, self.opts.device,
                                    self.landmark_bytes, self.retrieved.landmarks)
        return self._global

    def global_candidates(self) -> int:
        """How many landmarks the matches to every landmark compare: those of the retrieved photos."""
        return len(self.landmarks) if self.retrieved.landmarks is None else len(self.retrieved.landmarks)

    def global_focal_pose(self) -> FocalPose | None:
        """P4Pf (pose and focal length) on the matches to every landmark, found once: the features'
        focal verdict and the agreement check both read it."""
        if self._global_focal is None:
            li, ki = self.global_pairs()
            self._global_focal = (estimate_focal_pose(self.feats.uv[ki], self.landmarks.xyz[li], self.camera.width,
                                                      self.camera.height, self.opts.max_error_px, self.seed),)
        return self._global_focal[0]

    def agreement(self, R: np.ndarray, t: np.ndarray, camera: Camera) -> tuple[int, int] | None:
        """(how many of the matches to every landmark the pose (R, t) of `camera` explains within
        the features' PnP threshold, how many their own pose explains: P4Pf's inliers), or None when
        those matches give no pose with min_inliers. An answer that explains far fewer than their
        own pose does was found from a wrong start."""
        found = self.global_focal_pose() if self.use_global else None
        if found is None or int(found.inlier_mask.sum()) < self.opts.min_inliers:
            return None
        li, ki = self.global_pairs()
        explained = reprojection_inliers(camera, self.feats.uv[ki], self.landmarks.xyz[li], R, t, self.opts.max_error_px)
        return int(explained.sum()), int(found.inlier_mask.sum())

    def verified(self) -> VerifiedMatches | None:
        """SIFT + PnP's evidence (None for landmarks without observations)."""
        if self.landmarks.observations is None:
            return None
        if self._verified is None:
            self._verified = verified_matches(self.landmarks, self.feats, self.camera, self.seed,
                                              self.observation_desc, self.opts.threads, self.opts.device,
                                              self.keypoint_desc.get() if self.keypoint_desc is not None else None,
                                              self.focal_known, self.retrieved.images)
        return self._verified

    def verified_record(self) -> dict | None:
        return None if self._verified is None else self._verified.record()

    def verified_seconds(self) -> float | None:
        return None if self._verified is None else self._verified.seconds

    def focal_poses(self, global_matches: bool = True,
                    verified: bool = True) -> Iterator[tuple[np.ndarray, np.ndarray, FocalPose | None]]:
        """(uv, xyz, P4Pf on them) of the global matches (unless not use_global; their P4Pf found
        once, `global_focal_pose`), then of the verified ones."""
        if global_matches and self.use_global:
            li, ki = self.global_pairs()
            yield self.feats.uv[ki], self.landmarks.xyz[li], self.global_focal_pose()
        found = self.verified() if verified else None
        if found is not None:
            yield found.uv, found.xyz, estimate_focal_pose(found.uv, found.xyz, self.camera.width, self.camera.height,
                                                           self.opts.max_error_px, self.seed)
