"""The feature path, the one entry point of `usvc.relocalize.features`: refinement by features
(docs/method.md), the photo's SIFT keypoints matched to the map's landmarks. `Relocalizer` holds a
`FeaturePath` for its map's landmarks and calls, per photo:

1. `start`: the photo's SIFT (`sift`), found on the worker thread while the network runs;
2. `gather`, once the learned pose is found: the features, the mapping photos most like them
   (`retrieval`) and, on the worker, their matches to every landmark (`matching`);
3. `answer`: the hypotheses in order of cost (`refine_by_features`: guided passes from the learned
   pose; the matches to every landmark and SIFT + PnP's evidence when those find nothing; `passes`,
   `evidence`), the answer's last pass (`last_pass`), the focal length from P4Pf where none is
   given, the agreement check of a lone guided answer, and the features' verdict on a given focal
   length (`feature_focal_verdict`), found beside the guided passes;
4. `focal_verdict(verified=True)`, where the matches to every landmark cannot tell the focal
   length: SIFT + PnP's verified matches' verdict.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from usvc.core.absolute_pose import focal_log_std
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.camera_checks import FOCAL_SIGMAS, focal_reason, stretch_verdict
from usvc.relocalize.features.byte_products import ByteRows, scaled
from usvc.relocalize.features.device_matching import matching_device
from usvc.relocalize.features.evidence import QueryEvidence
from usvc.relocalize.features.last_pass import last_pass
from usvc.relocalize.features.matching import global_match_job
from usvc.relocalize.features.passes import (
    FeatureMatchOptions,
    FeatureResult,
    feature_options,
    from_global,
    from_prior,
    from_verified,
)
from usvc.relocalize.features.retrieval import ImageRetrieval, Retrieved
from usvc.relocalize.features.sift import QueryFeatures, QueryFeatureSet, SiftChoice, choose_sift, feature_job
from usvc.relocalize.features.verified_matching import HeldKeypointDescriptors, VerifiedMatches, observation_descriptors
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.pnp import PnPResult
from usvc.relocalize.query_cores import Job

FOCAL_UNOBSERVABLE = "unobservable"  # the features' focal verdict where they cannot tell (a shallow view)
# A guided answer that explains fewer than this share of the matches to every landmark that their
# own pose (P4Pf) explains was found from a wrong start (a learned pose off by ~10 degrees led bird's
# guided passes to a pose 6.5 degrees off with 218 inliers, explaining 33 of 76): the matches to
# every landmark then get their own hypothesis. Right answers explained 0.93-1.01 of them on office,
# bird and mini, from learned poses right or turned by up to 30 degrees (docs/results.md).
AGREEMENT = 0.8


def query_sift(options: RelocalizeOptions, device: str) -> SiftChoice:
    """The query's SIFT extractor and where it runs (`sift.choose_sift`), for a relocalizer on `device`."""
    return choose_sift(options.features_extractor, device, options.prior)


@dataclass
class PhotoFeatures:
    """A photo's features as `FeaturePath.gather` has them: the features, the mapping photos most
    like them (none retrieved with prior=none), and their matches to every landmark where those are
    being found already (on the worker thread)."""

    found: QueryFeatureSet
    retrieved: Retrieved
    global_pairs: Callable[[], tuple[np.ndarray, np.ndarray]] | None


class FeaturePath:
    """Refinement by features against one map's landmarks: what is held of them once per map (their
    descriptors as scaled rows and as bytes, the observations' descriptors per image, the mapping
    keypoints' descriptors, the image retrieval) and the relocalizer's options, device and seed. It
    keeps nothing of a query, so the photos localized at once share it."""

    def __init__(self, landmarks: Landmarks, options: RelocalizeOptions, device: str, seed: int) -> None:
        self.landmarks, self.options, self.device, self.seed = landmarks, options, device, seed
        self.prior = options.prior == "learned"  # prior=none: the learned pose guides nothing
        self.landmark_desc = scaled(landmarks.descriptor)  # matched by COLMAP's integer dots (`byte_products`)
        self.landmark_bytes = ByteRows.of(landmarks.descriptor)
        self.observation_desc = observation_descriptors(landmarks.observations) \
            if landmarks.observations is not None else None
        self.keypoint_desc = HeldKeypointDescriptors(landmarks.observations)  # SIFT + PnP's matching reads them
        self.retrieval = ImageRetrieval(landmarks)  # the mapping photos most like a query

    def start(self, gray01: np.ndarray, sift: SiftChoice) -> Job:
        """The photo's SIFT (`sift`: the extractor and where it runs, `query_sift`) on `gray01`
        (undistorted, at the photo's size), found on the worker thread while the network runs
        (`query_cores.Job`)."""
        return feature_job(gray01, self.landmarks.image_short_side, self.options.features_max_keypoints, sift)

    def gather(self, job: Job, check_focal: bool) -> PhotoFeatures:
        """The photo's features (`job`'s) once the learned pose is found; with the learned pose, the
        mapping photos most like them, which bound their matches to every landmark and the fallback
        (`retrieval`), and those matches, started on the worker (while the guided passes run) where a
        verdict or a fallback needs them: a focal length to estimate, or one to check (`check_focal`)."""
        found = job.result()
        retrieved = Retrieved()
        if self.prior:
            retrieved = self.retrieval.retrieve(found.feats, self.options.features_retrieval_images)
        global_pairs = None
        if self.prior and (not check_focal or self.options.focal_tolerance > 0):
            global_pairs = global_match_job(self.landmark_desc, found.feats, self.options.features_ratio,
                                            matching_device(self.device), landmark_bytes=self.landmark_bytes,
                                            rows=retrieved.landmarks).result
        return PhotoFeatures(found, retrieved, global_pairs)

    def answer(self, photo: PhotoFeatures, camera: Camera, dense: PnPResult, check_focal: bool,
               source: str = "") -> tuple[FeatureResult, str, Camera, QueryEvidence]:
        """Refinement by features on the undistorted photo's features (`photo.found`: found on the
        photo resized to the mapping images' short side when larger), `camera` the photo's at its own
        size, `dense` the learned pose; returns the result, why it is not trusted ("") and the camera
        it used, at the photo's size, and the evidence it weighed.

        Hypotheses in order of cost (`refine_by_features`): guided passes from the learned pose; when
        they find no pose (or with prior=none, or no learned pose), matching against every landmark's
        descriptor and SIFT + PnP's evidence (`verified_matches`); the one with the most support wins.
        Without given intrinsics (`check_focal` False) the focal length comes from P4Pf on
        correspondences that do not depend on it (`_estimate_focal`); with them, the features judge
        the given one (`focal_verdict`, `source` naming it)."""
        full, found_set = camera, photo.found
        feats = found_set.feats
        if found_set.resized:
            camera = camera.scaled(found_set.gray.shape[1], found_set.gray.shape[0])
        opts = feature_options(self.options, min(found_set.gray.shape), matching_device(self.device),
                               torch.get_num_threads())
        evidence = QueryEvidence(self.landmarks, self.landmark_desc, self.observation_desc, feats, opts, camera,
                                 self.seed, use_global=self.prior, global_pairs=photo.global_pairs,
                                 landmark_bytes=self.landmark_bytes, keypoint_desc=self.keypoint_desc,
                                 focal_known=check_focal, retrieved=photo.retrieved)
        prior = (dense.R, dense.t) if dense.success and self.prior else (None, None)
        verdict = None  # the features' focal verdict needs only the matches to every landmark: with more than
        if check_focal and self.options.focal_tolerance > 0 and evidence.use_global:  # one thread, it is
            verdict = Job(self.focal_verdict, evidence, source)  # found beside the guided passes
        if not check_focal:
            stretched, camera, full, prior = self._estimate_focal(evidence, opts, camera, full, prior)
            if stretched:
                return FeatureResult(None, None), stretched, full, evidence
        # a learned pose that too few cells agree with may lead the guided passes to a wrong pose: the
        # matches to every landmark get their chance too (computed already, for the focal verdict)
        weak = bool(dense.success and dense.num_inliers < self.options.min_confidence * len(dense.inlier_mask))
        agreement = None  # a guided answer checked against the matches to every landmark, where they are found anyway
        if evidence.use_global and photo.global_pairs is not None:
            def agreement(result: FeatureResult) -> tuple[int, int] | None:
                if verdict is not None:  # its P4Pf on those matches is the reference: found once, on its thread
                    verdict.result()
                return evidence.agreement(result.R, result.t, camera)
        found = self._hypotheses(feats, camera, prior, opts, evidence, weak, agreement)
        if not found.success or not check_focal or self.options.focal_tolerance <= 0:
            return found, "", full, evidence
        return found, verdict.result() if verdict is not None else self.focal_verdict(evidence, source), \
            full, evidence

    @staticmethod
    def _estimate_focal(evidence: QueryEvidence, opts: FeatureMatchOptions, camera: Camera, full: Camera,
                        prior: tuple) -> tuple[str, Camera, Camera, tuple]:
        """The photo's focal length from the first P4Pf with min_inliers on correspondences that do not
        depend on it (the matches to every landmark, else the verified ones): (why the photo looks
        stretched to them, "" when it does not; the camera at the features' size and at the photo's;
        the prior pose, P4Pf's where there is no learned one), unchanged where none gives one."""
        for uv, xyz, fp in evidence.focal_poses():
            if fp is None or int(fp.inlier_mask.sum()) < opts.min_inliers:
                continue
            stretched = stretch_verdict(uv, xyz, fp.camera, fp.R, fp.t, opts.max_error_px)
            if stretched:
                return stretched, camera, full, prior
            evidence.focal_estimated = True
            return "", fp.camera, fp.camera.scaled(full.width, full.height), (fp.R, fp.t) if prior[0] is None \
                else prior
        return "", camera, full, prior

    def _hypotheses(self, feats: QueryFeatures, camera: Camera, prior: tuple, opts: FeatureMatchOptions,
                    evidence: QueryEvidence, weak_prior: bool = False,
                    agreement: Callable[[FeatureResult], tuple[int, int] | None] | None = None) -> FeatureResult:
        found = refine_by_features(self.landmarks, self.landmark_desc, feats, camera, prior[0], prior[1], opts,
                                   self.seed, verified=evidence.verified, use_global=evidence.use_global,
                                   global_pairs=evidence.global_pairs, weak_prior=weak_prior, agreement=agreement,
                                   global_candidates=evidence.global_candidates())
        found = last_pass(found, self.landmarks, feats, camera, opts, self.observation_desc)
        found.verified = evidence.verified_record()
        found.verified_seconds = evidence.verified_seconds()
        return found

    def focal_verdict(self, evidence: QueryEvidence, source: str = "", verified: bool = False) -> str:
        """`feature_focal_verdict` at the relocalizer's focal_tolerance."""
        return feature_focal_verdict(evidence, self.options.focal_tolerance, source, verified)


def feature_focal_verdict(evidence: QueryEvidence, tolerance: float, source: str = "", verified: bool = False) -> str:
    """Why the photo's features contradict the given focal length ("" when they do not), or
    FOCAL_UNOBSERVABLE when they cannot tell. The focal length is estimated (P4Pf) on
    correspondences that do not depend on the given intrinsics (guided matches were picked by
    a projection with them): the matches to every landmark, or with `verified` SIFT + PnP's
    verified matches. Its inliers allow the focal lengths within FOCAL_SIGMAS standard
    deviations of the estimate (`focal_log_std`): none within `tolerance` (relative) of the given
    one refuses it, all of them vouch for it. A shallow view allows the given one and one
    (1 + tolerance)x off alike (the pose moves along the optical axis instead): then the
    features cannot tell."""
    camera, opts = evidence.camera, evidence.opts
    given = float(np.sqrt(camera.focal[0] * camera.focal[1]))
    band = 1.0 + tolerance
    for uv, xyz, found in evidence.focal_poses(global_matches=not verified, verified=verified):
        if found is None or int(found.inlier_mask.sum()) < opts.min_inliers:
            continue
        ratio = float(found.camera.params[0]) / given
        # the focal lengths the inliers allow: FOCAL_SIGMAS standard deviations either way
        spread = float(np.exp(min(FOCAL_SIGMAS * focal_log_std(found, uv, xyz), 50.0)))
        if ratio * spread < 1.0 / band or ratio / spread > band:  # none of them within the tolerance
            return focal_reason("the matched features imply", ratio, tolerance, source)
        if ratio * spread <= band and ratio / spread >= 1.0 / band:  # all of them within it
            return ""
        # else a shallow view: the matches allow the given focal length and one (1 + tol)x off alike
    return FOCAL_UNOBSERVABLE


def best_hypothesis(hypotheses: list[FeatureResult]) -> FeatureResult:
    """The hypothesis with the most PnP inliers after tightening (the first, the cheapest, on ties),
    carrying every hypothesis's passes and support in its record; or the last failure."""
    found = [h for h in hypotheses if h.success]
    best = max(found, key=lambda h: h.inliers) if found else FeatureResult(None, None)
    best = FeatureResult(best.R, best.t, best.inliers, best.matches, best.path, [], best.match_uv, best.match_xyz,
                         best.match_landmark, best.why, match_keypoint=best.match_keypoint)
    for h in hypotheses:
        best.passes.extend(h.passes)
    best.tried = [{"path": h.path or h.passes[0]["kind"], "inliers": h.inliers if h.success else 0,
                   **(h.agreement or {})} for h in hypotheses if h.passes]
    if not found:
        best.why = "; ".join(h.why for h in hypotheses if h.why) or "features: no match to the landmarks"
    return best


def refine_by_features(landmarks: Landmarks, lm_desc: np.ndarray, feats: QueryFeatures, camera: Camera,
                       R0: np.ndarray | None, t0: np.ndarray | None, opts: FeatureMatchOptions, seed: int = 0,
                       verified: Callable[[], VerifiedMatches | None] | None = None, use_global: bool = True,
                       global_pairs: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
                       weak_prior: bool = False,
                       agreement: Callable[[FeatureResult], tuple[int, int] | None] | None = None,
                       global_candidates: int | None = None) -> FeatureResult:
    """The pose of the query whose features are `feats` (pixels of `camera`'s image): guided passes
    from the learned pose (R0, t0) when there is one; when they find no pose (or there is no prior,
    or the prior is `weak_prior`: too few of the map's cells agree with it, so the guided passes
    may have settled on a wrong pose), matching against every landmark (unless not `use_global`;
    `global_pairs` gives those matches when they are computed already); when the guided passes find
    none, SIFT + PnP's evidence too (`verified`, called only then: it is the expensive one). The
    hypothesis with the most support wins. `lm_desc` are the landmarks' `byte_products.scaled` rows. The
    answer's last pass (opts.final) is `last_pass.last_pass`'s, after this. With `agreement` (how many of the
    matches to every landmark a result explains, and how many their own pose explains; None when
    they give no pose), a guided winner that did not compete with them is checked: one that explains
    fewer than AGREEMENT of what their own pose does competes with the global hypothesis, and the
    guided hypothesis's record says what the check found. `global_candidates`: how many landmarks
    `global_pairs` compared (those of the photos retrieved for the query; None: every one)."""
    hypotheses = []
    if R0 is not None and t0 is not None:
        hypotheses.append(from_prior(landmarks, lm_desc, feats, camera, R0, t0, opts, seed))
    guided = bool(hypotheses) and hypotheses[0].success
    if use_global and (not guided or weak_prior):
        hypotheses.append(from_global(landmarks, lm_desc, feats, camera, opts, seed,
                                      global_pairs() if global_pairs is not None else None, global_candidates))
    if not guided:
        found = verified() if verified is not None else None
        if found is not None:
            hypotheses.append(from_verified(landmarks, lm_desc, feats, camera, found, opts, seed))
    best = best_hypothesis(hypotheses)
    if best.success and best.path == "guided" and use_global and agreement is not None and len(hypotheses) == 1:
        agree = agreement(best)
        if agree is not None:
            hypotheses[0].agreement = {"global_matches_explained": agree[0], "by_their_own_pose": agree[1]}
            if agree[0] < AGREEMENT * agree[1]:  # a wrong start: the matches to every landmark get their say
                hypotheses.append(from_global(landmarks, lm_desc, feats, camera, opts, seed,
                                              global_pairs() if global_pairs is not None else None, global_candidates))
            best = best_hypothesis(hypotheses)
    return best
