"""Keyframes of a dense posed capture: the mapping frames SfM runs on.

A video-like capture repeats the same view many times; each repeat adds matching pairs and track
observations to SfM but no new information. Frames are taken in name (capture) order and a frame
is kept unless some keyframe already kept lies within `sfm.keyframe_min_translation` of it (a
fraction of the capture's size: the median distance of the camera centres from their centroid)
AND within `sfm.keyframe_min_rotation_deg` of its orientation. Captures of at most
`sfm.keyframe_min_images` mapping frames keep every frame, and a threshold of 0 turns selection
off. The dropped frames stay mapping frames (their poses are known): later stages train on them,
without SfM observations of their own.
"""

from __future__ import annotations

import logging

import numpy as np

from usvc.core.scene import Frame
from usvc.sfm.options import SfmOptions

log = logging.getLogger(__name__)


def capture_scale(centers: np.ndarray) -> float:
    """The capture's size: the median distance of the camera centres (N, 3) from their centroid."""
    return float(np.median(np.linalg.norm(centers - centers.mean(0), axis=1)))


def select_keyframes(frames: list[Frame], min_translation: float, min_rotation_deg: float) -> list[bool]:
    """Whether each frame (in the given order) is a keyframe: greedy in name order, a frame is dropped
    when a kept keyframe is both within `min_translation` x capture_scale of its centre and within
    `min_rotation_deg` of its orientation. The first frame is always kept; 0 for either threshold keeps all."""
    n = len(frames)
    if n == 0 or min_translation <= 0 or min_rotation_deg <= 0:
        return [True] * n
    order = sorted(range(n), key=lambda i: frames[i].name)
    centers = np.stack([np.asarray(f.center, np.float64) for f in frames])
    rotations = np.stack([np.asarray(f.R, np.float64) for f in frames])
    max_dist = min_translation * capture_scale(centers)
    # The angle between rotations A and B is below θ iff trace(A B^T) > 1 + 2 cos θ.
    min_trace = 1.0 + 2.0 * np.cos(np.radians(min(min_rotation_deg, 180.0)))
    keep = [False] * n
    kept: list[int] = []
    for i in order:
        if kept:
            k = np.asarray(kept)
            near = np.linalg.norm(centers[k] - centers[i], axis=1) < max_dist
            if near.any():
                trace = np.einsum("kab,ab->k", rotations[k[near]], rotations[i])
                if (trace > min_trace).any():
                    continue
        keep[i] = True
        kept.append(i)
    return keep


def mapping_keyframes(frames: list[Frame], opts: SfmOptions, has_poses: bool) -> list[Frame]:
    """The frames SfM runs on: every frame of a capture without poses or of at most
    sfm.keyframe_min_images frames, else the keyframes (select_keyframes), in the given order."""
    if not has_poses or len(frames) <= opts.keyframe_min_images:
        return list(frames)
    keep = select_keyframes(frames, opts.keyframe_min_translation, opts.keyframe_min_rotation_deg)
    out = [f for f, k in zip(frames, keep) if k]
    log.info("sfm: %d keyframes of %d mapping frames (sfm.keyframe_min_translation=%g of the capture's size, "
             "sfm.keyframe_min_rotation_deg=%g)", len(out), len(frames), opts.keyframe_min_translation,
             opts.keyframe_min_rotation_deg)
    return out
