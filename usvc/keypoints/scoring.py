"""Scene keypoint selection (paper eq. 1-3): keep 3D points whose descriptors agree across views.

M(X) = sum_i w_i exp(-|phi(X) - d_i|^2 / (2 sigma^2)), phi(X) the mean descriptor, keep M >= tau.
Descriptors are L2-normalised SIFT, so distances live in [0, 2] and sigma is in those units.
With uniform weights M is a soft count of views that agree with the mean, so tau = 1.5 asks for
at least two consistent views; `reprojection` weights additionally discount observations that
the triangulated point does not reproject onto.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usvc.core.errors import KeypointError
from usvc.core.h5io import write_h5
from usvc.sfm.tracks import Tracks, write_images_group


@dataclass(frozen=True)
class KeypointOptions:
    tau: float
    sigma: float
    weights: str
    reprojection_scale_px: float
    min_track_length: int


def normalise(descriptors: np.ndarray) -> np.ndarray:
    d = descriptors.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def observation_weights(tracks: Tracks, opts: KeypointOptions) -> np.ndarray:
    if opts.weights == "uniform":
        return np.ones(len(tracks.obs_error), dtype=np.float32)
    if opts.weights == "reprojection":
        return 1.0 / (1.0 + (tracks.obs_error / opts.reprojection_scale_px) ** 2)
    raise KeypointError(f"unknown keypoints.weights {opts.weights!r}")


def score_points(tracks: Tracks, opts: KeypointOptions) -> tuple[np.ndarray, np.ndarray]:
    """Matching score M(X) and mean descriptor phi(X) of every point, segment-wise in numpy."""
    length = tracks.track_length
    if np.any(length == 0):
        raise KeypointError("tracks contain a point without observations")
    d = normalise(tracks.obs_descriptor)
    starts = tracks.offset[:-1]
    phi = np.add.reduceat(d, starts, axis=0) / length[:, None]
    dist2 = np.sum((d - np.repeat(phi, length, axis=0)) ** 2, axis=1)
    q = np.exp(-dist2 / (2.0 * opts.sigma**2))
    score = np.add.reduceat(observation_weights(tracks, opts) * q, starts).astype(np.float64)
    score[length < opts.min_track_length] = 0.0
    return score, phi.astype(np.float32)


@dataclass
class Keypoints:
    index: np.ndarray  # rows of the kept points in the tracks
    score: np.ndarray  # (N,) score of every point, kept or not
    mean_descriptor: np.ndarray  # (K,128) of the kept points


def select_keypoints(tracks: Tracks, opts: KeypointOptions) -> Keypoints:
    score, phi = score_points(tracks, opts)
    keep = np.flatnonzero(score >= opts.tau)
    if len(keep) == 0:
        raise KeypointError(
            f"keypoints.tau={opts.tau} keeps no keypoint (max score {score.max():.3f} over "
            f"{len(score)} points); lower tau or raise sigma"
        )
    return Keypoints(index=keep, score=score, mean_descriptor=phi[keep])


def keypoint_stats(kp: Keypoints, tracks: Tracks, opts: KeypointOptions) -> dict:
    edges = np.linspace(0.0, max(float(kp.score.max()), opts.tau) + 1e-9, 11)
    hist, _ = np.histogram(kp.score, bins=edges)
    kept_len = tracks.track_length[kp.index]
    return {
        "tau": opts.tau,
        "sigma": opts.sigma,
        "weights": opts.weights,
        "points": int(len(kp.score)),
        "kept": int(len(kp.index)),
        "kept_fraction": float(len(kp.index) / len(kp.score)),
        "kept_mean_track_length": float(kept_len.mean()),
        "score_median": float(np.median(kp.score)),
        "score_histogram": {"edges": [round(float(e), 4) for e in edges], "counts": hist.tolist()},
    }


def write_keypoints(path: Path, kp: Keypoints, tracks: Tracks) -> None:
    """Kept points with their observations (image, uv), so later stages need only this file."""
    length = tracks.track_length[kp.index]
    kept = np.zeros(len(tracks.xyz), dtype=bool)
    kept[kp.index] = True
    obs_rows = np.flatnonzero(np.repeat(kept, tracks.track_length))
    with write_h5(path) as h5:
        write_images_group(h5, tracks)
        k = h5.create_group("keypoints")
        k["id"] = tracks.point_id[kp.index]
        k["xyz"] = tracks.xyz[kp.index]
        k["rgb"] = tracks.rgb[kp.index]
        k["score"] = kp.score[kp.index]
        k["mean_descriptor"] = kp.mean_descriptor
        k["track_offset"] = np.concatenate([[0], np.cumsum(length)]).astype(np.int64)
        obs = h5.create_group("obs")
        obs["image"] = tracks.obs_image[obs_rows]
        obs["uv"] = tracks.obs_uv[obs_rows]
