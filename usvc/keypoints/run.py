"""The keypoints step: score every SfM point by descriptor consistency (paper eq. 1-3) and keep
M >= tau -> keypoints.h5 (and keypoints.ply, for viewers)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from usvc.core.artifact_names import KEYPOINTS_H5, KEYPOINTS_PLY
from usvc.core.points_file import write_points_ply
from usvc.keypoints.keypoints_file import write_keypoints
from usvc.keypoints.options import KeypointOptions
from usvc.keypoints.scoring import keypoint_stats, select_keypoints
from usvc.sfm.tracks_file import read_tracks

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    tracks: Path  # the SfM model (sfm/tracks.h5)


def run(inputs: Inputs, out: Path, options: KeypointOptions) -> dict:
    """Write the kept keypoints into `out`; returns the step's figures."""
    tracks = read_tracks(inputs.tracks)
    kp = select_keypoints(tracks, options)
    write_keypoints(out / KEYPOINTS_H5, kp, tracks)
    write_points_ply(out / KEYPOINTS_PLY, tracks.xyz[kp.index], tracks.rgb[kp.index],
                     score=kp.score[kp.index].astype("float32"))
    stats = keypoint_stats(kp, tracks, options)
    log.info("keypoints: kept %d of %d points at tau=%g", stats["kept"], stats["points"], options.tau)
    return stats
