"""Stage: render novel views around keypoint clusters from the 3DGS model, with keypoint observations."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.scene_file import read_scene_h5
from usvc.keypoints.keypoints_file import read_scene_keypoints
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import (
    peak_memory_mb,
    scene_paths,
    skip_unless_rendered_views,
    stage_main,
    stage_outputs,
)
from usvc.render.novel_views import render_novel_views
from usvc.render.views_file import write_rendered_views
from usvc.splat.ply_file import read_splat_ply

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    if skip_unless_rendered_views(cfg, "render"):
        return
    t0 = time.perf_counter()
    paths = scene_paths(cfg)
    model = read_splat_ply(paths.gaussians / "splat.ply")
    frames = read_scene_h5(paths.prepared).split("train")
    keypoints = read_scene_keypoints(paths.keypoints / "keypoints.h5")
    opts = group_options(cfg, "render")
    views, stats = render_novel_views(model, frames, keypoints, opts, tile=cfg.gaussians.tile)
    out, metrics_path = stage_outputs(cfg, "render")
    with atomic_dir(out) as tmp:
        write_rendered_views(tmp, views)
    stats.update({"computed": True, "seed": opts.seed, "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb(),
                  "width": int(views[0].rgb.shape[1]), "height": int(views[0].rgb.shape[0])})
    write_json(metrics_path, stats)
    log.info("render %s: %d views, %.0f visible keypoints per view, %.1f deg from the source on average, %.0f s",
             cfg.scene.name, stats["views"], stats["mean_visible_keypoints"], stats["mean_angle_deg"], stats["seconds"])


if __name__ == "__main__":
    main()
