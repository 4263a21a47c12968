"""The relocalizer's answer from the photo's features (refinement by features, docs/method.md): the
hypotheses in order of cost (guided passes from the learned pose; the matches to every landmark and
SIFT + PnP's evidence when those find nothing), the focal length from P4Pf where none is given, the
agreement check of a lone guided answer and the focal verdict found beside the guided passes.
`FeatureAnswers` is the part of `Relocalizer` that makes it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.byte_products import ByteRows
from usvc.relocalize.camera_checks import stretch_verdict
from usvc.relocalize.device_matching import matching_device
from usvc.relocalize.feature_job import Job, QueryFeatureSet
from usvc.relocalize.feature_refinement import FeatureMatchOptions, FeatureResult, feature_options, refine_by_features
from usvc.relocalize.image_retrieval import Retrieved
from usvc.relocalize.last_pass import last_pass
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.query_evidence import QueryEvidence
from usvc.relocalize.query_features import QueryFeatures
from usvc.relocalize.verified_matching import HeldKeypointDescriptors


class FeatureAnswers:
    """Refinement by features for `Relocalizer` (whose loaded map, landmarks and options it reads)."""

    options: RelocalizeOptions
    landmarks: Landmarks | None
    device: str
    seed: int
    prior: bool
    _landmark_desc: np.ndarray
    _landmark_bytes: ByteRows
    _observation_desc: list[ByteRows] | None
    _keypoint_desc: HeldKeypointDescriptors

    def _features(self, found_set: QueryFeatureSet, global_pairs: Callable[[], tuple[np.ndarray, np.ndarray]] | None,
                  camera: Camera, dense, check_focal: bool,
                  source: str = "", retrieved: Retrieved = Retrieved()) -> tuple[FeatureResult, str, Camera, QueryEvidence]:
        """Refinement by features on the undistorted photo's features (`found_set`: found on the
        photo resized to the mapping images' short side when larger; `global_pairs` gives their
        matches to every landmark when they are being found already); returns the result, why it is not trusted ("") and the camera it used,
        at the photo's size.

        Hypotheses in order of cost: guided passes from the learned pose; when they find no pose
        (or with prior=none, or no learned pose), matching against every landmark's descriptor and
        SIFT + PnP's evidence (`verified_matches`), each tightened by guided passes; the one with
        the most support wins. Without given intrinsics (`check_focal` False) the focal length
        comes from P4Pf on correspondences that do not depend on it (the global matches, else the
        verified ones) where they give one, and they also tell whether the photo was stretched."""
        assert self.landmarks is not None
        full = camera
        feats = found_set.feats
        if found_set.resized:
            camera = camera.scaled(found_set.gray.shape[1], found_set.gray.shape[0])
        opts = feature_options(self.options, min(found_set.gray.shape), matching_device(self.device),
                               torch.get_num_threads())
        evidence = QueryEvidence(self.landmarks, self._landmark_desc, self._observation_desc, feats, opts, camera,
                                 self.seed, use_global=self.prior, global_pairs=global_pairs,
                                 landmark_bytes=self._landmark_bytes, keypoint_desc=self._keypoint_desc,
                                 focal_known=check_focal, retrieved=retrieved)
        prior = (dense.R, dense.t) if dense.success and self.prior else (None, None)
        verdict = None  # the features' focal verdict needs only the matches to every landmark: with more than
        if check_focal and self.options.focal_tolerance > 0 and evidence.use_global:  # one thread, it is
            verdict = Job(self._feature_focal_verdict, evidence, source)  # found beside the guided passes
        if not check_focal:
            for uv, xyz, fp in evidence.focal_poses():
                if fp is None or int(fp.inlier_mask.sum()) < opts.min_inliers:
                    continue
                stretched = stretch_verdict(uv, xyz, fp.camera, fp.R, fp.t, opts.max_error_px)
                if stretched:
                    return FeatureResult(None, None), stretched, full, evidence
                camera = fp.camera
                full = camera.scaled(full.width, full.height)
                evidence.focal_estimated = True
                prior = (fp.R, fp.t) if prior[0] is None else prior
                break
        # a learned pose that too few cells agree with may lead the guided passes to a wrong pose: the
        # matches to every landmark get their chance too (computed already, for the focal verdict)
        weak = bool(dense.success and dense.num_inliers < self.options.min_confidence * len(dense.inlier_mask))
        agreement = None  # a guided answer checked against the matches to every landmark, where they are found anyway
        if evidence.use_global and global_pairs is not None:
            def agreement(result: FeatureResult) -> tuple[int, int] | None:
                if verdict is not None:  # its P4Pf on those matches is the reference: found once, on its thread
                    verdict.result()
                return evidence.agreement(result.R, result.t, camera)
        found = self._hypotheses(feats, camera, prior, opts, evidence, weak, agreement)
        if not found.success or not check_focal or self.options.focal_tolerance <= 0:
            return found, "", full, evidence
        return found, verdict.result() if verdict is not None else self._feature_focal_verdict(evidence, source), \
            full, evidence

    def _hypotheses(self, feats: QueryFeatures, camera: Camera, prior: tuple, opts: FeatureMatchOptions,
                    evidence: QueryEvidence, weak_prior: bool = False,
                    agreement: Callable[[FeatureResult], tuple[int, int] | None] | None = None) -> FeatureResult:
        assert self.landmarks is not None
        found = refine_by_features(self.landmarks, self._landmark_desc, feats, camera, prior[0], prior[1], opts,
                                   self.seed, verified=evidence.verified, use_global=evidence.use_global,
                                   global_pairs=evidence.global_pairs, weak_prior=weak_prior, agreement=agreement,
                                   global_candidates=evidence.global_candidates())
        found = last_pass(found, self.landmarks, feats, camera, opts, self._observation_desc)
        found.verified = evidence.verified_record()
        found.verified_seconds = evidence.verified_seconds()
        return found
