"""The relocalizer's verdicts on a given focal length: which evidence judges it (the photo's matches
to every landmark, the map's coordinates where the map reads the photo and tells focal lengths,
SIFT + PnP's verified matches), in that order, and why a focal length is refused
(docs/confidence.md). `FocalVerdicts` is the part of `Relocalizer` that holds them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from usvc.core.absolute_pose import estimate_focal, focal_log_std
from usvc.core.geometry import camera_centers
from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.camera_checks import FOCAL_SIGMAS
from usvc.relocalize.feature_refinement import FeatureResult
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.pnp import PnPResult
from usvc.relocalize.query_evidence import QueryEvidence

FOCAL_UNOBSERVABLE = "unobservable"
FOCAL_UNCHECKED = ("the given focal length was not checked: this view is too shallow for the photo's features to "
                   "tell it, and the map did not read the photo well enough to; a wrong one would move the pose "
                   "along the optical axis")
MAP_DOES_NOT_JUDGE = ("the given focal length was not checked: this map does not tell its own photos' focal lengths "
                      "within focal_tolerance (a longer training lets it)")
FOCAL_UNCHECKED_MAP = (MAP_DOES_NOT_JUDGE + ", and this view is too shallow for the photo's features to; a wrong one "
                       "would move the pose along the optical axis")
# The learned pose "describes" the photo when it is this close to the feature pose.
AGREE_DEG, AGREE_DEPTH_FRACTION = 15.0, 0.5


def poses_agree(R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray, median_depth: float) -> bool:
    """Whether two world-to-camera poses are the same view up to what a coarse map gets wrong:
    within AGREE_DEG of rotation and AGREE_DEPTH_FRACTION of the median scene depth apart."""
    cos = (np.trace(R1 @ R2.T) - 1.0) / 2.0
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    gap = float(np.linalg.norm(camera_centers(R1, t1) - camera_centers(R2, t2)))
    return angle <= AGREE_DEG and gap <= AGREE_DEPTH_FRACTION * median_depth


def focal_reason(evidence: str, ratio: float, tolerance: float, source: str) -> str:
    """Why a given focal length is refused; `source` names where it came from (e.g. EXIF)."""
    if source:
        return (f"{source} disagrees with the photo's content: {evidence} a focal length {ratio:.2f}x it "
                f"(tolerance {tolerance:g})")
    return f"{evidence} a focal length {ratio:.2f}x the given one (tolerance {tolerance:g}); check the intrinsics"


class FocalVerdicts:
    """The focal-length verdicts of a `Relocalizer` (which sets these attributes)."""

    options: RelocalizeOptions
    seed: int
    prior: bool
    map_judges_focal: bool
    median_depth: float
    landmarks: Landmarks | None

    def _focal_disagreement(self, pixels: np.ndarray, coords: np.ndarray, camera: Camera, threshold: float,
                            tolerance: float | None = None, source: str = "",
                            map_focal: Callable[[], Camera | None] | None = None) -> str:
        """Why the given focal length cannot be right ("" when it can): the map's scene coordinates
        imply another one (beyond `tolerance`, default focal_tolerance). A wrong focal length can
        still explain most cells with a wrong pose (a shallow view trades focal length for
        distance), so confidence alone cannot catch it. `map_focal` gives that estimate when it
        was started already (`usvc.relocalize.feature_job.Job`)."""
        tolerance = self.options.focal_tolerance if tolerance is None else tolerance
        estimate = map_focal() if map_focal is not None else estimate_focal(
            pixels, coords.reshape(-1, 3), camera.width, camera.height, threshold, self.seed)
        if estimate is None:
            return ""  # no opinion: nothing to hold against the given focal length
        given = float(np.sqrt(camera.focal[0] * camera.focal[1]))
        ratio = estimate.params[0] / given
        if abs(np.log(ratio)) <= np.log1p(tolerance):
            return ""
        return focal_reason("the image implies", ratio, tolerance, source)

    def _focal_without_global_evidence(self, dense: PnPResult, feature: FeatureResult, evidence: QueryEvidence,
                                       pixels: np.ndarray, coords: np.ndarray, camera: Camera | None,
                                       threshold: float, cells: int, source: str,
                                       map_focal: Callable[[], Camera | None] | None = None) -> str:
        """Why the given focal length is wrong ("" when it is right, FOCAL_UNOBSERVABLE when nothing
        tells) when the matches to every landmark cannot tell, from the next evidence in order: the
        map's coordinates where they read this photo well (the learned pose agrees with the features' and min_confidence of the
        cells agree with it); else SIFT + PnP's verified matches (P4Pf); else the map's coordinates
        where the learned pose at least agrees with the features'. The map judges at a wider
        tolerance since it is coarse ((1 + tol)^2 - 1: 0.56 at 0.25, so a 2x wrong focal still
        fails); a photo it cannot read (turned sideways) gives it no say, nor does a map that does
        not tell its own views' focal lengths within the tolerance (`map_judges_focal`)."""
        if not self.map_judges_focal:  # a shallow view of a map that cannot judge: SIFT + PnP's matches
            return FOCAL_UNOBSERVABLE  # would cost a second and cannot tell either (docs/confidence.md)
        agree = bool(self.prior and dense.success and feature.success and camera is not None
                     and poses_agree(dense.R, dense.t, feature.R, feature.t, self.median_depth))
        wide = (1.0 + self.options.focal_tolerance) ** 2 - 1.0
        if agree and dense.num_inliers >= self.options.min_confidence * cells:
            assert camera is not None
            return self._focal_disagreement(pixels, coords, camera, threshold, wide, source, map_focal)
        verdict = self._feature_focal_verdict(evidence, source, verified=True)
        feature.verified, feature.verified_seconds = evidence.verified_record(), evidence.verified_seconds()
        if verdict != FOCAL_UNOBSERVABLE:
            return verdict
        if agree:
            assert camera is not None
            return self._focal_disagreement(pixels, coords, camera, threshold, wide, source, map_focal)
        return FOCAL_UNOBSERVABLE  # nothing tells: nothing contradicts the given focal length either

    def _unsupported_focal(self, camera: Camera, dense_inliers: int, cells: int, from_map: bool) -> str:
        """Why a feature pose of a photo without intrinsics is no answer: its focal length came
        neither from the photo's features (P4Pf) nor from a map that reads the photo (min_confidence
        of the cells agreeing), so nothing supports the camera the pose was solved with."""
        source = (f"the map's coordinates, which only {dense_inliers} of the {cells} cells agree with (confidence "
                  f"{dense_inliers / cells:.3f} < min_confidence {self.options.min_confidence:g})" if from_map
                  else "no evidence (the map's coordinates gave none)")
        return (f"no focal length to trust: the one the pose was solved with ({camera.focal[0]:.4g} px) comes from "
                f"{source}, and the photo's features give none: stretched, cropped or not of this place? Give its "
                "intrinsics")

    def _feature_focal_verdict(self, evidence: QueryEvidence, source: str = "", verified: bool = False) -> str:
        """Why the photo's features contradict the given focal length ("" when they do not), or
        FOCAL_UNOBSERVABLE when they cannot tell. The focal length is estimated (P4Pf) on
        correspondences that do not depend on the given intrinsics (guided matches were picked by
        a projection with them): the matches to every landmark, or with `verified` SIFT + PnP's
        verified matches. Its inliers allow the focal lengths within FOCAL_SIGMAS standard
        deviations of the estimate (`focal_log_std`): none within the tolerance of the given one
        refuses it, all of them vouch for it. A shallow view allows the given one and one
        (1 + focal_tolerance)x off alike (the pose moves along the optical axis instead): then the
        features cannot tell."""
        assert self.landmarks is not None
        tol = self.options.focal_tolerance
        camera, opts = evidence.camera, evidence.opts
        given = float(np.sqrt(camera.focal[0] * camera.focal[1]))
        band = 1.0 + tol
        for uv, xyz, found in evidence.focal_poses(global_matches=not verified, verified=verified):
            if found is None or int(found.inlier_mask.sum()) < opts.min_inliers:
                continue
            ratio = float(found.camera.params[0]) / given
            # the focal lengths the inliers allow: FOCAL_SIGMAS standard deviations either way
            spread = float(np.exp(min(FOCAL_SIGMAS * focal_log_std(found, uv, xyz), 50.0)))
            if ratio * spread < 1.0 / band or ratio / spread > band:  # none of them within the tolerance
                return focal_reason("the matched features imply", ratio, tol, source)
            if ratio * spread <= band and ratio / spread >= 1.0 / band:  # all of them within it
                return ""
            # else a shallow view: the matches allow the given focal length and one (1 + tol)x off alike
        return FOCAL_UNOBSERVABLE
