"""Stage: score every SfM point by descriptor consistency (paper eq. 1-3) and keep M >= tau."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.points_file import write_points_ply
from usvc.keypoints.keypoints_file import write_keypoints
from usvc.keypoints.scoring import keypoint_stats, select_keypoints
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.sfm.tracks import read_tracks

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    tracks = read_tracks(scene_paths(cfg).sfm / "tracks.h5")
    opts = group_options(cfg, "keypoints")
    kp = select_keypoints(tracks, opts)
    out, metrics_path = stage_outputs(cfg, "keypoints")
    with atomic_dir(out) as tmp:
        write_keypoints(tmp / "keypoints.h5", kp, tracks)
        write_points_ply(tmp / "keypoints.ply", tracks.xyz[kp.index], tracks.rgb[kp.index],
                         score=kp.score[kp.index].astype("float32"))
    stats = {**keypoint_stats(kp, tracks, opts), "seconds": time.perf_counter() - t0,
             "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, stats)
    log.info("keypoints %s: kept %d of %d points at tau=%g", cfg.scene.name, stats["kept"], stats["points"], opts.tau)


if __name__ == "__main__":
    main()
