"""Stage: SIFT + matching + triangulation (poses fixed) of the mapping images with pycolmap."""

import logging
import tempfile
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.points_file import write_points_ply
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.sfm.reconstruction import reconstruct
from usvc.sfm.tracks import from_reconstruction, sfm_stats, write_tracks

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    prepared = scene_paths(cfg).prepared
    scene = read_scene_h5(prepared)
    opts = group_options(cfg, "sfm")
    out, metrics_path = stage_outputs(cfg, "sfm")
    with atomic_dir(out) as tmp, tempfile.TemporaryDirectory(prefix="usvc-sfm-") as work:
        rec, info = reconstruct(scene.split("train"), prepared / IMAGE_DIR, Path(work), opts, scene.has_poses)
        tracks = from_reconstruction(rec, Path(work) / "database.db")
        (tmp / "model").mkdir()
        rec.write(tmp / "model")
        write_tracks(tmp / "tracks.h5", tracks)
        write_points_ply(tmp / "points.ply", tracks.xyz, tracks.rgb)
    stats = {**sfm_stats(tracks), **info, "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, stats)
    log.info("sfm %s: %d points, track length %.2f, reprojection %.3f px (median %.3f), %.1f s",
             cfg.scene.name, stats["points"], stats["mean_track_length"], stats["mean_reprojection_error_px"],
             stats["median_reprojection_error_px"], stats["seconds"])


if __name__ == "__main__":
    main()
