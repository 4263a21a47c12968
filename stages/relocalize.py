"""Stage: relocalize the scene's query images with its map -> poses.txt, queries.h5/json."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.errors import UsvcError
from usvc.core.scene_file import read_scene_h5
from usvc.landmarks.landmarks_file import LANDMARKS_FILE
from usvc.model.head import read_map_header
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.relocalize.relocalize_scene import relocalize_frames, write_results
from usvc.relocalize.relocalizer import Relocalizer

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    paths = scene_paths(cfg)
    frames = read_scene_h5(paths.prepared).split("test")
    options = group_options(cfg, "relocalize")
    mapped = read_map_header(paths.map / "map.pt")["metadata"].get("scene")
    if cfg.scene.name != mapped:
        raise UsvcError(f"{paths.map / 'map.pt'} is a map of scene {mapped!r}, not of {cfg.scene.name!r}: "
                        "rerun the train stage for this scene")
    relocalizer = Relocalizer(paths.map / "map.pt", cfg.model.encoder_weights, options, seed=cfg.seed,
                              landmarks=paths.landmarks / LANDMARKS_FILE if options.refine == "features" else None)
    results = relocalize_frames(relocalizer, frames)
    out, metrics_path = stage_outputs(cfg, "relocalize")
    with atomic_dir(out) as tmp:
        stats = write_results(tmp, frames, results)
    write_json(metrics_path, {**stats, "precision": relocalizer.precision,
                              "map_precision": relocalizer.metadata.get("precision", "fp32"),
                              "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()})
    log.info("relocalize %s (%s): %d queries, %d failed, %.0f ms/query", cfg.scene.name, relocalizer.precision,
             stats["queries"], stats["failed"], stats["ms_per_query"])


if __name__ == "__main__":
    main()
