"""Stage: import the scene from its source format and resize images to the working resolution."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, stage_main, stage_outputs
from usvc.prepare.importers import load_scene
from usvc.prepare.importers.photos import skipped_entries
from usvc.prepare.working_images import prepare_scene

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    sc = cfg.scene
    t0 = time.perf_counter()
    scene = load_scene(sc.format, sc.path, sc.name, sc.split, sc.split_n, sc.metric_scale, sc.exif_focal)
    out, metrics_path = stage_outputs(cfg, "prepared")
    with atomic_dir(out) as tmp:
        stats = prepare_scene(scene, tmp, sc.working_width, sc.undistort_fov, group_options(cfg, "sfm"))
    if sc.format == "images":  # what the photo folder held besides photos (logged by the importer too)
        stats["skipped"] = skipped_entries(scene.root)
    write_json(metrics_path, {**stats, "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()})


if __name__ == "__main__":
    main()
