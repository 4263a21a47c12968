"""Landmarks: position, one SIFT descriptor, and where the point was seen from (built from the SfM
tracks by usvc.landmarks.build).

A landmark is a triangulated SfM point with a single descriptor standing for its track (the mean
of the track's unit descriptors, as Active Search keeps per point, or the track's medoid), the
mean direction from the point to the cameras that saw it, and the widest angle between that
direction and any of them. At query time a landmark is a candidate only when the camera sees it
from within that cone (plus a margin): a point on the far side of an object is not matched.

Each landmark also keeps its track: every mapping image that observed it, with that observation's
keypoint and descriptor, and the mapping images' cameras (`LandmarkObservations`). They are the
evidence SIFT + PnP uses (the query's keypoints matched to each mapping image's keypoints, the
matches verified per pair, lifted to the points through the tracks): the relocalizer falls back
on them when the learned pose does not lead to the photo's features. With them come every keypoint
of the mapping images (`MappingKeypoints`), those that observe no point too: SIFT + PnP's ratio and
mutual tests compare a query's keypoint with all of a mapping photo's.

Descriptors are COLMAP's SIFT (L1-root normalised) in its uint8 encoding (512 x value, clipped
at 255); `unit_descriptors` turns them into unit vectors for matching.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usvc.core.errors import UsvcError

DESCRIPTOR_SCALE = 512.0  # COLMAP's uint8 SIFT encoding


@dataclass
class MappingKeypoints:
    """Every SIFT keypoint of the mapping images, those that observe no point included, grouped by
    image: what SIFT + PnP matches a query against (its ratio and mutual tests see every keypoint
    of a mapping photo; the matches of those with a point are then lifted through it)."""

    image: np.ndarray  # (K,) int32 row of LandmarkObservations.image_names
    uv: np.ndarray  # (K,2) float32 keypoint, COLMAP pixel convention
    descriptor: np.ndarray  # (K,128) uint8 SIFT descriptor (COLMAP's encoding)
    landmark: np.ndarray  # (K,) int32 row of the landmark the keypoint observes, -1 for none

    def problems(self, n_landmarks: int, n_images: int) -> list[str]:
        k = len(self.image)
        shapes = {"keypoint landmark": (self.landmark.shape, (k,)), "keypoint uv": (self.uv.shape, (k, 2)),
                  "keypoint descriptor": (self.descriptor.shape, (k, 128))}
        out = [f"{name} {got}, expected {want}" for name, (got, want) in shapes.items() if got != want]
        if out:
            return out
        if k and (self.landmark.min() < -1 or self.landmark.max() >= n_landmarks):
            out.append(f"a keypoint names a landmark outside -1..{n_landmarks - 1}")
        if k and (self.image.min() < 0 or self.image.max() >= n_images):
            out.append(f"a keypoint names an image outside 0..{n_images - 1}")
        if k > 1 and np.any(np.diff(self.image) < 0):
            out.append("keypoints are not grouped by image")
        if not np.isfinite(self.uv).all():
            out.append("keypoints are not finite")
        return out

    def image_slices(self) -> list[tuple[int, int, int]]:
        """(image row, first keypoint, end) of every image with keypoints, in image order."""
        return _slices(self.image)


def _slices(image: np.ndarray) -> list[tuple[int, int, int]]:
    if len(image) == 0:
        return []
    starts = np.flatnonzero(np.r_[True, image[1:] != image[:-1]])
    ends = np.r_[starts[1:], len(image)]
    return [(int(image[a]), int(a), int(b)) for a, b in zip(starts, ends)]


@dataclass
class LandmarkObservations:
    """Every observation of the landmarks in the mapping images, grouped by image (rows of one image
    are contiguous, images in order), and the mapping images' pinhole cameras."""

    landmark: np.ndarray  # (T,) int32 row of the observed landmark
    image: np.ndarray  # (T,) int32 row of image_names: the mapping image of the observation
    uv: np.ndarray  # (T,2) float32 keypoint, COLMAP pixel convention, in that image
    descriptor: np.ndarray  # (T,128) uint8 SIFT descriptor of the keypoint (COLMAP's encoding)
    image_names: list[str]  # (M,) mapping image names
    image_K: np.ndarray  # (M,3,3) float64 intrinsics of each mapping image (pinhole, prepared size)
    image_size: np.ndarray  # (M,2) int32 width, height of each mapping image
    keypoints: MappingKeypoints | None = None  # every keypoint of the images (absent before format version 3)

    def problems(self, n_landmarks: int) -> list[str]:
        t, m = len(self.landmark), len(self.image_names)
        shapes = {"obs landmark": (self.landmark.shape, (t,)), "obs image": (self.image.shape, (t,)),
                  "obs uv": (self.uv.shape, (t, 2)), "obs descriptor": (self.descriptor.shape, (t, 128)),
                  "image K": (self.image_K.shape, (m, 3, 3)), "image size": (self.image_size.shape, (m, 2))}
        out = [f"{k} {got}, expected {want}" for k, (got, want) in shapes.items() if got != want]
        if out:
            return out
        if t and (self.landmark.min() < 0 or self.landmark.max() >= n_landmarks):
            out.append(f"an observation names a landmark outside 0..{n_landmarks - 1}")
        if t and (self.image.min() < 0 or self.image.max() >= m):
            out.append(f"an observation names an image outside 0..{m - 1}")
        if t > 1 and np.any(np.diff(self.image) < 0):
            out.append("observations are not grouped by image")
        if not (np.isfinite(self.uv).all() and np.isfinite(self.image_K).all()):
            out.append("observations or cameras are not finite")
        if self.keypoints is not None:
            out += self.keypoints.problems(n_landmarks, m)
        return out

    def image_slices(self) -> list[tuple[int, int, int]]:
        """(image row, first observation, end) of every image with observations, in image order."""
        return _slices(self.image)


@dataclass
class Landmarks:
    scene: str  # the scene whose SfM model they come from
    xyz: np.ndarray  # (N,3) float64 world positions (the SfM points, bit for bit)
    descriptor: np.ndarray  # (N,128) uint8, COLMAP's SIFT encoding
    view_dir: np.ndarray  # (N,3) float32 unit mean direction from the point to its cameras
    view_angle_deg: np.ndarray  # (N,) float32 widest angle between view_dir and a camera that saw it
    track_length: np.ndarray  # (N,) int32 observations of the point
    image_short_side: int  # median short side (px) of the mapping images the descriptors come from
    observations: LandmarkObservations | None = None  # the tracks (absent in files of format version 1)
    words: np.ndarray | None = None  # (W,128) float32 visual words of the mapping photos' unit descriptors (`usvc.core.vlad`), or None

    def __post_init__(self) -> None:
        n = len(self.xyz)
        shapes = {"xyz": (self.xyz.shape, (n, 3)), "descriptor": (self.descriptor.shape, (n, 128)),
                  "view_dir": (self.view_dir.shape, (n, 3)), "view_angle_deg": (self.view_angle_deg.shape, (n,)),
                  "track_length": (self.track_length.shape, (n,))}
        bad = [f"{k} {got}, expected {want}" for k, (got, want) in shapes.items() if got != want]
        if bad:
            raise UsvcError(f"landmarks of scene {self.scene!r} are inconsistent: {'; '.join(bad)}")
        if not (np.isfinite(self.xyz).all() and np.isfinite(self.view_dir).all()
                and np.isfinite(self.view_angle_deg).all()):
            raise UsvcError(f"landmarks of scene {self.scene!r} have non-finite positions or directions")
        if self.observations is not None:
            bad = self.observations.problems(n)
            if bad:
                raise UsvcError(f"landmarks of scene {self.scene!r} have inconsistent observations: {'; '.join(bad)}")
        if self.words is not None and (self.words.ndim != 2 or self.words.shape[1] != 128 or len(self.words) == 0
                                       or not np.isfinite(self.words).all()):
            raise UsvcError(f"landmarks of scene {self.scene!r}: retrieval words of shape {self.words.shape}, "
                            "expected (W, 128) finite with W >= 1")
        if self.image_short_side <= 0:
            raise UsvcError(f"landmarks of scene {self.scene!r}: image_short_side must be positive, "
                            f"got {self.image_short_side}")

    def __len__(self) -> int:
        return len(self.xyz)


def unit_descriptors(descriptor: np.ndarray) -> np.ndarray:
    """uint8 (or float) SIFT descriptors -> float32 unit rows (zero rows stay zero)."""
    d = np.asarray(descriptor, dtype=np.float32)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(n, 1e-12)


def encode_descriptors(unit: np.ndarray) -> np.ndarray:
    """Unit float descriptors -> COLMAP's uint8 encoding."""
    return np.clip(np.round(np.asarray(unit, dtype=np.float64) * DESCRIPTOR_SCALE), 0, 255).astype(np.uint8)


def image_descriptors(obs: LandmarkObservations) -> list[np.ndarray]:
    """Each mapping image's SIFT descriptors as unit float32 rows: every keypoint where the
    observations carry them, else its observations; in image order (images without any: empty)."""
    rows = obs.keypoints if obs.keypoints is not None else obs
    out = [np.zeros((0, 128), np.float32) for _ in obs.image_names]
    for image, a, b in rows.image_slices():
        out[image] = unit_descriptors(rows.descriptor[a:b])
    return out
