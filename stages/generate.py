"""Stage: render the miniature synthetic scene (ACE layout) into scene.path."""

import logging
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from usvc.core.errors import UsvcError
from usvc.generate.writer import generate_scene
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import (
    is_multirun,
    job_dir,
    peak_memory_mb,
    scene_paths,
    stage_main,
)

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    if not cfg.scene.generated:
        raise UsvcError(f"scene {cfg.scene.name!r} is not a generated scene (scene.generated=false)")
    out = job_dir() / "raw" if is_multirun() else Path(cfg.scene.path)
    t0 = time.perf_counter()
    stats = generate_scene(out, group_options(cfg, "generate"))
    metrics = {**stats, "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()}
    write_json(job_dir() / "metrics.json" if is_multirun() else scene_paths(cfg).metrics("generate"), metrics)
    log.info("generated %s in %.1f s", out, metrics["seconds"])


if __name__ == "__main__":
    main()
