"""Build landmarks from the sfm stage's tracks (the landmarks stage's step)."""

from __future__ import annotations

import logging

import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.geometry import camera_centers
from usvc.core.vlad import vocabulary
from usvc.landmarks.landmark_table import (
    LandmarkObservations,
    Landmarks,
    MappingKeypoints,
    encode_descriptors,
    image_descriptors,
    unit_descriptors,
)
from usvc.landmarks.options import LandmarksOptions
from usvc.sfm.tracks_file import Tracks

log = logging.getLogger(__name__)


def _track_descriptors(tracks: Tracks, keep: np.ndarray, how: str) -> np.ndarray:
    """One unit descriptor per kept point: the renormalised mean or the medoid of its track."""
    unit = unit_descriptors(tracks.obs_descriptor)
    point = tracks.point_of_obs()
    n = len(tracks.xyz)
    mean = np.zeros((n, 128), dtype=np.float64)
    np.add.at(mean, point, unit)
    mean = unit_descriptors(mean)
    if how == "mean":
        return mean[keep]
    # medoid: the observation closest to its track's mean direction (the most central one under
    # cosine distance for unit vectors); ties go to the first observation.
    closeness = np.einsum("ij,ij->i", unit, mean[point])
    best = np.full(n, -1, dtype=np.int64)
    order = np.lexsort((-closeness, point))  # per point, the closest first
    first = np.ones(len(order), dtype=bool)
    first[1:] = point[order][1:] != point[order][:-1]
    best[point[order][first]] = order[first]
    return unit[best[keep]]


def _view_cones(tracks: Tracks, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean unit direction from each kept point to its observing cameras, and the widest angle."""
    centers = camera_centers(tracks.R, tracks.t)
    point = tracks.point_of_obs()
    rays = centers[tracks.obs_image] - tracks.xyz[point]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    mean = np.zeros((len(tracks.xyz), 3))
    np.add.at(mean, point, rays)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    cos = np.clip(np.einsum("ij,ij->i", rays, mean[point]), -1.0, 1.0)
    widest = np.zeros(len(tracks.xyz))
    np.maximum.at(widest, point, np.degrees(np.arccos(cos)))
    return mean[keep].astype(np.float32), widest[keep].astype(np.float32)


def landmark_observations(tracks: Tracks, keep: np.ndarray, image_sizes: np.ndarray) -> LandmarkObservations:
    """Every observation of the kept points (rows `keep` of tracks), grouped by mapping image;
    `image_sizes` (M,2) are the width and height of tracks' images, in tracks' order."""
    point = tracks.point_of_obs()
    row_of_point = np.full(len(tracks.xyz), -1, dtype=np.int64)
    row_of_point[keep] = np.arange(len(keep))
    landmark = row_of_point[point]
    sel = np.flatnonzero(landmark >= 0)
    sel = sel[np.lexsort((sel, np.asarray(tracks.obs_image)[sel]))]  # by image, then as in tracks: stable
    return LandmarkObservations(landmark=landmark[sel].astype(np.int32),
                                image=np.asarray(tracks.obs_image)[sel].astype(np.int32),
                                uv=np.asarray(tracks.obs_uv, np.float32)[sel],
                                descriptor=np.asarray(tracks.obs_descriptor, np.uint8)[sel],
                                image_names=list(tracks.image_names), image_K=np.asarray(tracks.K, np.float64),
                                image_size=np.asarray(image_sizes, np.int32).reshape(-1, 2),
                                keypoints=mapping_keypoints(tracks, row_of_point))


def mapping_keypoints(tracks: Tracks, row_of_point: np.ndarray) -> MappingKeypoints | None:
    """Every keypoint of tracks' images (None for tracks without them), each naming the landmark
    row of its point (`row_of_point`, -1 for points left out) or -1."""
    if tracks.kp_image is None or tracks.kp_uv is None or tracks.kp_descriptor is None or tracks.kp_point is None:
        return None
    point = np.asarray(tracks.kp_point, np.int64)
    landmark = np.where(point >= 0, row_of_point[np.maximum(point, 0)], -1)
    return MappingKeypoints(image=np.asarray(tracks.kp_image, np.int32), uv=np.asarray(tracks.kp_uv, np.float32),
                            descriptor=np.asarray(tracks.kp_descriptor, np.uint8).reshape(-1, 128),
                            landmark=landmark.astype(np.int32))


def retrieval_words(obs: LandmarkObservations, words: int, seed: int = 0) -> np.ndarray | None:
    """`words` visual words of the mapping images' descriptors (seeded k-means: the same words for
    the same model), or None with no words asked for or no descriptor."""
    descriptors = [d for d in image_descriptors(obs) if len(d)]
    if words <= 0 or not descriptors:
        return None
    return vocabulary(descriptors, words, seed)


def build_landmarks(tracks: Tracks, scene: str, image_short_side: int, opts: LandmarksOptions,
                    image_sizes: np.ndarray | None = None) -> Landmarks:
    """The landmarks of one SfM model (points in the order of tracks.h5, filtered by `opts`), with
    their observations when `image_sizes` ((M,2) width, height of tracks' mapping images) is given."""
    length = tracks.track_length
    keep = (length >= opts.min_track_length) & (tracks.error <= opts.max_error_px)
    keep_idx = np.flatnonzero(keep)
    if opts.max_landmarks and len(keep_idx) > opts.max_landmarks:
        # longest tracks first (seen from most images, the most likely to be seen again); stable
        order = np.argsort(-length[keep_idx], kind="stable")[: opts.max_landmarks]
        keep_idx = np.sort(keep_idx[order])
    if len(keep_idx) < 4:
        raise UsvcError(f"scene {scene!r}: only {len(keep_idx)} SfM points qualify as landmarks "
                        f"(landmarks.min_track_length={opts.min_track_length}, "
                        f"landmarks.max_error_px={opts.max_error_px:g}); a pose needs at least 4")
    desc = _track_descriptors(tracks, keep_idx, opts.descriptor)
    view_dir, view_angle = _view_cones(tracks, keep_idx)
    log.info("landmarks %s: %d of %d SfM points (%s descriptors)", scene, len(keep_idx), len(tracks.xyz),
             opts.descriptor)
    observations = None if image_sizes is None else landmark_observations(tracks, keep_idx, image_sizes)
    return Landmarks(scene=scene, xyz=tracks.xyz[keep_idx].astype(np.float64), descriptor=encode_descriptors(desc),
                     view_dir=view_dir, view_angle_deg=view_angle,
                     track_length=length[keep_idx].astype(np.int32), image_short_side=int(image_short_side),
                     observations=observations,
                     words=None if observations is None else retrieval_words(observations, opts.retrieval_words))


def landmark_stats(landmarks: Landmarks, tracks: Tracks) -> dict:
    return {"landmarks": len(landmarks), "points": int(len(tracks.xyz)),
            "mean_track_length": float(landmarks.track_length.mean()),
            "median_view_angle_deg": float(np.median(landmarks.view_angle_deg)),
            "image_short_side": landmarks.image_short_side,
            "observations": 0 if landmarks.observations is None else len(landmarks.observations.landmark),
            "mapping_keypoints": 0 if landmarks.observations is None or landmarks.observations.keypoints is None
            else len(landmarks.observations.keypoints.image)}
