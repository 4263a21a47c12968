"""Stage: encoder features of augmented mapping views, sampled per view, into buffer.h5."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.buffer.build import (
    HELDOUT_FILE,
    fill_buffer,
    fill_heldout,
    holdout_split,
    working_short_side,
    write_buffer,
)
from usvc.core.atomic import atomic_dir
from usvc.core.scene_file import read_depth, read_scene_h5
from usvc.keypoints.keypoints_file import read_scene_keypoints
from usvc.model.encoder import encoder_fingerprint
from usvc.pipeline.config import group_options, register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.render.views_file import read_rendered_views
from usvc.weights import load_configured_encoder

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    paths = scene_paths(cfg)
    scene = read_scene_h5(paths.prepared)
    frames, holdout = holdout_split(scene.split("train"), cfg.buffer.holdout_every)
    index = {f.name: i for i, f in enumerate(scene.frames)}
    depths = [read_depth(paths.prepared, index[f.name]) for f in frames]
    keypoints = read_scene_keypoints(paths.keypoints / "keypoints.h5")
    n_rendered = 0
    if cfg.buffer.rendered_views:
        rendered, observations = read_rendered_views(paths.render)
        frames, depths, n_rendered = frames + rendered, depths + [None] * len(rendered), len(rendered)
        keypoints.by_image.update(observations)
    encoder, weights = load_configured_encoder(cfg.model.encoder_width, cfg.model.encoder_weights,
                                               cfg.model.encoder)
    b = cfg.buffer
    short_side = working_short_side(min(frames[0].camera.width, frames[0].camera.height), b.short_side,
                                    cfg.model.max_short_side)
    buf = fill_buffer(frames, encoder, group_options(cfg, "buffer"), short_side, seed=cfg.seed, keypoints=keypoints,
                      depths=depths if any(d is not None for d in depths) else None,
                      mapping_images=len(frames) - n_rendered)
    # Held-out mapping images, unaugmented: training measures its held-out fit on them (train.validate_every).
    heldout = fill_heldout(holdout, encoder, group_options(cfg, "buffer"), short_side, seed=cfg.seed) if holdout else None
    out, metrics_path = stage_outputs(cfg, "buffer")
    attrs = {"short_side": short_side, "encoder_file": weights.name, "encoder_fingerprint": encoder_fingerprint(encoder)}
    with atomic_dir(out) as tmp:
        write_buffer(tmp / "buffer.h5", buf, **attrs)
        if heldout is not None:
            write_buffer(tmp / HELDOUT_FILE, heldout, **attrs)
        megabytes = (tmp / "buffer.h5").stat().st_size / 2**20
    stats = {"cells": len(buf.features), "views": len(buf.view_image), "mapping_images": len(frames) - n_rendered,
             "rendered_images": n_rendered,
             "holdout_images": len(holdout), "holdout_cells": 0 if heldout is None else len(heldout.features),
             "rendered_buffer_views": int((buf.view_image >= len(frames) - n_rendered).sum()),
             "short_side": short_side, "feature_dim": int(buf.features.shape[1]), "megabytes": megabytes,
             "encoder": weights.name, "keypoint_observations": len(buf.kp_id),
             "keypoints_observed": int(len(set(buf.kp_id.tolist()))), "keypoints_kept": len(buf.keypoint_xyz),
             "keypoint_observations_from_depth": int(buf.kp_from_depth.sum()), "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()}
    write_json(metrics_path, stats)
    log.info("buffer %s: %d cells from %d views in %.1f s", cfg.scene.name, stats["cells"], stats["views"],
             stats["seconds"])


if __name__ == "__main__":
    main()
