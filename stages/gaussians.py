"""Stage: fit a 3D Gaussian splatting model to the mapping images; splat PLY + held-out PSNR/SSIM."""

import logging

import cv2
import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.scene_file import read_scene_h5
from usvc.gaussians.fit import fit_gaussians, load_fit_images, split_holdout
from usvc.gaussians.stage_fit import (
    initial_gaussians,
    ply_reload_difference,
)
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import (
    peak_memory_mb,
    scene_paths,
    skip_unless_rendered_views,
    stage_main,
    stage_outputs,
)
from usvc.sfm.tracks import read_tracks
from usvc.splat.ply_file import write_splat_ply
from usvc.splat.rasterize import render

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    if skip_unless_rendered_views(cfg, "gaussians"):
        return
    paths = scene_paths(cfg)
    opts = group_options(cfg, "gaussians")
    tracks = read_tracks(paths.sfm / "tracks.h5")
    images = load_fit_images(read_scene_h5(paths.prepared).split("train"), opts.width)
    init = initial_gaussians(tracks, opts.sh_degree, opts.initial_opacity)
    log.info("gaussians %s: fitting %d initial Gaussians to %d images at %dx%d, %d iterations", cfg.scene.name,
             len(init), len(images), images[0].view.width, images[0].view.height, opts.iterations)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    result = fit_gaussians(init, images, opts, device=device)
    out, metrics_path = stage_outputs(cfg, "gaussians")
    _, held = split_holdout(images, opts.holdout_every)
    check = held[0] if held else images[0]
    with atomic_dir(out) as tmp:
        write_splat_ply(tmp / "splat.ply", result.gaussians)
        reload_diff = ply_reload_difference(tmp / "splat.ply", result.gaussians, check, opts.tile)
        with torch.no_grad():
            pred = render(result.gaussians, check.view, tile=opts.tile).rgb.clamp(0, 1).numpy()
        side = np.concatenate([pred, check.rgb.numpy()], axis=1)
        cv2.imwrite(str(tmp / "heldout_render_vs_image.png"), (side[..., ::-1] * 255).round().astype(np.uint8))
        megabytes = (tmp / "splat.ply").stat().st_size / 2**20
    metrics = {"computed": True, **result.metrics, "device": device, "ply_megabytes": megabytes, "ply_reload_max_abs_diff": reload_diff,
               "seed": opts.seed, "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, metrics)
    log.info("gaussians %s: %d Gaussians, held-out PSNR %.2f dB, SSIM %.3f, fit %.0f s", cfg.scene.name,
             metrics["gaussians"], metrics["heldout_psnr"] or float("nan"), metrics["heldout_ssim"] or float("nan"),
             metrics["fit_seconds"])


if __name__ == "__main__":
    main()
