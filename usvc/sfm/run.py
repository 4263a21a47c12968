"""The sfm step: SIFT, matching and triangulation (poses given) or incremental mapping of the
mapping images with pycolmap -> the COLMAP model, tracks.h5 and points.ply."""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

from usvc.core.artifact_names import POINTS_PLY, TRACKS_H5
from usvc.core.points_file import write_points_ply
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.sfm.options import SfmOptions
from usvc.sfm.reconstruction import reconstruct
from usvc.sfm.tracks_file import from_reconstruction, sfm_stats, write_tracks

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    scene: Path  # the prepared scene (prepared/scene.h5; its images beside it)


def run(inputs: Inputs, out: Path, options: SfmOptions, *, threads: int) -> dict:
    """Reconstruct the scene's mapping images into `out` (feature extraction on `threads` threads
    unless sfm.num_threads is set); returns the model's figures and the step's timings."""
    scene = read_scene_h5(inputs.scene)
    with tempfile.TemporaryDirectory(prefix="usvc-sfm-") as work:
        rec, info = reconstruct(scene.split("train"), inputs.scene.parent / IMAGE_DIR, Path(work), options,
                                scene.has_poses, threads=threads)
        tracks = from_reconstruction(rec, Path(work) / "database.db")
        (out / "model").mkdir()
        rec.write(out / "model")
        write_tracks(out / TRACKS_H5, tracks)
        write_points_ply(out / POINTS_PLY, tracks.xyz, tracks.rgb)
    stats = {**sfm_stats(tracks), **info}
    log.info("sfm: %d points, track length %.2f, reprojection %.3f px (median %.3f)", stats["points"],
             stats["mean_track_length"], stats["mean_reprojection_error_px"], stats["median_reprojection_error_px"])
    return stats
