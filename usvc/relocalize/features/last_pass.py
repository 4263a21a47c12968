"""The answer's last pass (`relocalize.features_final`), after refinement by features has chosen
the evidence that found the photo (`path.refine_by_features`): SIFT + PnP's own
per-image matching around the answer (`verified_matching.pose_checked_matches`), either to
weight the answer's matches by the mapping images that confirm them (`confirmed`, the default) or
to replace them (`images`); `guided` keeps the guided passes' pose. SIFT + PnP's own path
("verified") is that evidence already and gets no last pass."""

from __future__ import annotations

import numpy as np

from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import Landmarks
from usvc.relocalize.counted_refinement import distinct_pairs
from usvc.relocalize.features.byte_products import ByteRows
from usvc.relocalize.features.passes import VERIFIED_MAX_ERROR_PX, FeatureMatchOptions, FeatureResult, accept
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import VerifiedMatches, pose_checked_matches
from usvc.relocalize.pnp import project_points, refine_on_inliers

# The confirmed pass's pose check and refinement threshold, px at the mapping images' size: twice SIFT
# + PnP's. The matches it confirms are the guided passes' (accepted at features_max_error_px), from a
# pose a few px off on hard queries: at 4 px one bird query kept 35 of its 200 matches and its answer
# moved by 1-7 rel cm with the RANSAC seed; at 8 px every figure held on all three seeds (docs/results.md).
CONFIRM_MAX_ERROR_PX = 8.0


def _images_evidence(out: FeatureResult, landmarks: Landmarks, feats: QueryFeatures, camera: Camera,
                     opts: FeatureMatchOptions, image_descriptors: list[ByteRows] | None,
                     max_error_px: float = VERIFIED_MAX_ERROR_PX) -> tuple[VerifiedMatches, float]:
    """SIFT + PnP's per-image matches around `out`'s answer (`pose_checked_matches`: the mapping
    images that observe the landmarks it explains, each image's matches verified by its pose within
    `max_error_px` at the mapping images' size, so only the keypoints within that of a landmark are
    compared), and that threshold in px of the query's feature image."""
    assert out.R is not None and out.t is not None
    uv, _ = project_points(camera, out.match_xyz, out.R, out.t)
    seen = out.match_landmark[np.linalg.norm(uv - out.match_uv, axis=1) <= opts.max_error_px]
    max_error = max_error_px * min(camera.width, camera.height) / landmarks.image_short_side
    found = pose_checked_matches(landmarks, feats, camera, out.R, out.t, seen, max_error, image_descriptors,
                                 opts.threads, opts.device, opts.final_images, opts.final_comparisons)
    return found, max_error


def images_pass(out: FeatureResult, landmarks: Landmarks, feats: QueryFeatures, camera: Camera,
                opts: FeatureMatchOptions, image_descriptors: list[ByteRows] | None = None) -> None:
    """The answer's last pass with SIFT + PnP's evidence around it (relocalize.features_final=images):
    the per-image matches of `_images_evidence` replace the answer's matches, and the pose is refined
    on those within VERIFIED_MAX_ERROR_PX again under each new pose (the Cauchy loss of COLMAP's
    refinement, the last step of SIFT + PnP's LO-RANSAC), each keypoint counted once per image it
    matched in, as SIFT + PnP counts it: each distinct (keypoint, landmark) pair once, weighted by that
    count (`counted_refinement`, the same objective at a tenth of the cost). That count is what makes
    the baseline's pose the more precise one on mini: its correspondences counted once each gave a
    worse median (docs/results.md). Its pose check is SIFT + PnP's VERIFIED_MAX_ERROR_PX: twice that
    compared ~2x the keypoints for the same answers to a few per cent of the median (docs/results.md).
    Replaces `out`'s pose when at least min_inliers distinct keypoints support the new one."""
    found, max_error = _images_evidence(out, landmarks, feats, camera, opts, image_descriptors)
    rows, counts = distinct_pairs(found.keypoint, found.landmark)  # a pair once, weighted by its repetitions
    res = refine_on_inliers(found.uv[rows], found.xyz[rows], camera, out.R, out.t, max_error,
                            counts=counts) if len(found) >= opts.min_inliers else None
    support = 0 if res is None or not res.success else int(len(np.unique(found.keypoint[rows][res.inlier_mask])))
    out.passes.append({"kind": "images", "radius_px": None, "candidates": int(found.images),
                       "matches": int(len(found)), "distinct_matches": int(len(rows)),
                       "verified_pairs": int(found.verified_pairs), "inliers": support})
    if support >= opts.min_inliers:
        accept(out, res, feats, found.keypoint[rows], landmarks, found.landmark[rows], support)
        out.matches = len(found)


def confirmations(keypoint: np.ndarray, landmark: np.ndarray, found_keypoint: np.ndarray,
                  found_landmark: np.ndarray) -> np.ndarray:
    """For each match (keypoint[i], landmark[i]): how many of the found correspondences (one per
    mapping image that gave it) are that same (keypoint, landmark) pair; 0 where none is."""
    keypoint, landmark = np.asarray(keypoint, np.int64), np.asarray(landmark, np.int64)
    if len(keypoint) == 0 or len(found_keypoint) == 0:
        return np.zeros(len(keypoint), np.int64)
    base = int(max(np.max(landmark), np.max(found_landmark))) + 1
    keys, counts = np.unique(np.asarray(found_keypoint, np.int64) * base + np.asarray(found_landmark, np.int64),
                             return_counts=True)
    mine = keypoint * base + landmark
    at = np.minimum(np.searchsorted(keys, mine), len(keys) - 1)
    return np.where(keys[at] == mine, counts[at], 0)


def keypoint_sites(uv: np.ndarray) -> np.ndarray:
    """Each keypoint's site: the first keypoint at exactly its position (SIFT gives a location one
    keypoint per dominant orientation, each with its own descriptor, all the same measurement)."""
    if len(uv) == 0:
        return np.zeros(0, np.int64)
    _, first, inverse = np.unique(np.asarray(uv), axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int64)


def confirmed_pass(out: FeatureResult, landmarks: Landmarks, feats: QueryFeatures, camera: Camera,
                   opts: FeatureMatchOptions, image_descriptors: list[ByteRows] | None = None) -> None:
    """The answer's last pass (relocalize.features_final=confirmed, the default): each of the
    answer's own matches weighted by the number of mapping images in which SIFT + PnP's per-image
    matching (`_images_evidence`: nearest observation by descriptor, ratio and mutual tests against
    every visible observation of the image, the answer's pose within CONFIRM_MAX_ERROR_PX) finds
    that same (keypoint site, landmark) pair; a match no image confirms is dropped. The pose is
    refined on the confirmed matches within CONFIRM_MAX_ERROR_PX (`refine_on_inliers` with those
    counts: the objective SIFT + PnP's refinement would have over the repetitions, whose Cauchy loss
    of 1 px scale leaves the far ones little weight). The baseline's weighting on
    the guided matches: on mini, bird and office at least SIFT + PnP's precision, where its own
    matches instead of the guided ones (`images_pass`) lose a bird query at (2cm,2°) (docs/results.md).
    Replaces `out`'s pose when at least min_inliers confirmed keypoints support the new one."""
    found, max_error = _images_evidence(out, landmarks, feats, camera, opts, image_descriptors, CONFIRM_MAX_ERROR_PX)
    site = keypoint_sites(feats.uv)  # SIFT's orientations of one location are one measurement
    weight = confirmations(site[out.match_keypoint], out.match_landmark, site[found.keypoint], found.landmark)
    kept = np.flatnonzero(weight > 0)
    res = refine_on_inliers(out.match_uv[kept], out.match_xyz[kept], camera, out.R, out.t, max_error,
                            counts=weight[kept]) if len(kept) >= opts.min_inliers else None
    support = 0 if res is None or not res.success else int(len(np.unique(out.match_keypoint[kept][res.inlier_mask])))
    out.passes.append({"kind": "confirmed", "radius_px": None, "candidates": int(found.images),
                       "matches": int(len(out.match_keypoint)), "confirmed": int(len(kept)),
                       "confirmations": int(weight.sum()), "verified_pairs": int(found.verified_pairs),
                       "inliers": support})
    if support >= opts.min_inliers:
        accept(out, res, feats, out.match_keypoint[kept], landmarks, out.match_landmark[kept], support)


def last_pass(answer: FeatureResult, landmarks: Landmarks, feats: QueryFeatures, camera: Camera,
              opts: FeatureMatchOptions, image_descriptors: list[ByteRows] | None = None) -> FeatureResult:
    """`answer` after opts.final's last pass (`confirmed_pass` or `images_pass`; none for `guided`),
    where it has a pose from the guided or global path and the landmarks carry their observations
    (`image_descriptors`: their descriptors per image, `verified_matching.observation_descriptors`, held
    once per map)."""
    if opts.final != "guided" and answer.success and answer.path != "verified" and landmarks.observations is not None:
        (images_pass if opts.final == "images" else confirmed_pass)(answer, landmarks, feats, camera, opts,
                                                                      image_descriptors)
    return answer
