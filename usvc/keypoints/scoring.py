"""Scene keypoint selection (paper eq. 1-3): keep 3D points whose descriptors agree across views.

M(X) = sum_i w_i exp(-|phi(X) - d_i|^2 / (2 sigma^2)), phi(X) the mean descriptor, keep M >= tau.
Descriptors are L2-normalised SIFT, so distances live in [0, 2] and sigma is in those units.
With uniform weights M is a soft count of views that agree with the mean, so tau = 1.5 asks for
at least two consistent views; `reprojection` weights additionally discount observations that
the triangulated point does not reproject onto.
"""

from __future__ import annotations

import numpy as np

from usvc.core.errors import KeypointError
from usvc.keypoints.keypoints_file import Keypoints
from usvc.keypoints.options import KeypointOptions
from usvc.sfm.tracks_file import Tracks


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
