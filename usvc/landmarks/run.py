"""The landmarks step: the SfM points with one SIFT descriptor each -> landmarks.h5, which
query-time feature refinement matches the query's SIFT against."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.core.scene_file import read_scene_h5
from usvc.landmarks.build import build_landmarks, landmark_stats
from usvc.landmarks.landmarks_file import write_landmarks
from usvc.landmarks.options import LandmarksOptions
from usvc.sfm.tracks_file import read_tracks

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    tracks: Path  # the SfM model (sfm/tracks.h5)
    scene: Path  # the prepared scene (prepared/scene.h5): the mapping images' sizes


def run(inputs: Inputs, out: Path, options: LandmarksOptions, *, scene: str) -> dict:
    """Write the landmarks of `scene` into `out`; returns the step's figures."""
    tracks = read_tracks(inputs.tracks)
    mapping = read_scene_h5(inputs.scene).split("train")
    short_side = int(np.median([min(f.camera.width, f.camera.height) for f in mapping]))
    size = {f.name: (f.camera.width, f.camera.height) for f in mapping}
    missing = [n for n in tracks.image_names if n not in size]
    if missing:
        raise UsvcError(f"{inputs.tracks}: mapping image {missing[0]!r} is not in {inputs.scene}: "
                        "the SfM model is of another scene (rerun the sfm stage)")
    landmarks = build_landmarks(tracks, scene, short_side, options, np.array([size[n] for n in tracks.image_names]))
    write_landmarks(out / LANDMARKS_H5, landmarks)
    megabytes = (out / LANDMARKS_H5).stat().st_size / 2**20
    stats = {**landmark_stats(landmarks, tracks), "megabytes": megabytes}
    log.info("landmarks: %d landmarks, %d observations, %.2f MB", stats["landmarks"], stats["observations"],
             megabytes)
    return stats
