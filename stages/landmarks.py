"""Stage: the SfM points with one SIFT descriptor each -> landmarks.h5 (feature refinement)."""

import logging
import time

import hydra
import numpy as np
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.scene_file import read_scene_h5
from usvc.landmarks.build import build_landmarks, landmark_stats
from usvc.landmarks.landmarks_file import LANDMARKS_FILE, write_landmarks
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
    paths = scene_paths(cfg)
    tracks = read_tracks(paths.sfm / "tracks.h5")
    mapping = read_scene_h5(paths.prepared).split("train")
    short_side = int(np.median([min(f.camera.width, f.camera.height) for f in mapping]))
    landmarks = build_landmarks(tracks, cfg.scene.name, short_side, group_options(cfg, "landmarks"))
    out, metrics_path = stage_outputs(cfg, "landmarks")
    with atomic_dir(out) as tmp:
        write_landmarks(tmp / LANDMARKS_FILE, landmarks)
        megabytes = (tmp / LANDMARKS_FILE).stat().st_size / 2**20
    stats = {**landmark_stats(landmarks, tracks), "megabytes": megabytes, "seconds": time.perf_counter() - t0,
             "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, stats)
    log.info("landmarks %s: %d landmarks, %.2f MB", cfg.scene.name, stats["landmarks"], megabytes)


if __name__ == "__main__":
    main()
