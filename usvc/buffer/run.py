"""The buffer step: encoder features of augmented mapping views, sampled per view, with their
scene-coordinate targets and keypoint tuples -> buffer.h5 (and holdout.h5: cells of withheld
mapping images, for training's held-out fit)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from usvc.buffer.buffer_file import write_buffer
from usvc.buffer.build import fill_buffer, fill_heldout, holdout_split, working_short_side
from usvc.buffer.options import BufferOptions
from usvc.core.artifact_names import BUFFER_H5, HOLDOUT_H5
from usvc.core.scene_file import DepthMaps, read_scene_h5
from usvc.keypoints.keypoints_file import read_scene_keypoints
from usvc.model.encoder import encoder_fingerprint
from usvc.model.options import ModelOptions
from usvc.render.views_file import read_rendered_views
from usvc.weights import load_configured_encoder

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    scene: Path  # the prepared scene (prepared/scene.h5): mapping images, cameras, depth maps
    keypoints: Path  # the kept keypoints (keypoints/keypoints.h5)
    render: Path  # the rendered views (render/render.h5), read when buffer.rendered_views is true


def run(inputs: Inputs, out: Path, options: BufferOptions, model: ModelOptions, *, seed: int,
        device: str = "cpu") -> dict:
    """Fill the buffer with `model`'s encoder (run on `device`) into `out`; returns its figures."""
    scene = read_scene_h5(inputs.scene)
    frames, holdout = holdout_split(scene.split("train"), options.holdout_every)
    index = {f.name: i for i, f in enumerate(scene.frames)}
    keypoints = read_scene_keypoints(inputs.keypoints)
    n_rendered = 0
    if options.rendered_views:
        rendered, observations = read_rendered_views(inputs.render)
        frames, n_rendered = frames + rendered, len(rendered)
        keypoints.by_image.update(observations)
    encoder, weights = load_configured_encoder(model.encoder_width, model.encoder_weights, model.encoder)
    short_side = working_short_side(min(frames[0].camera.width, frames[0].camera.height), options.short_side,
                                    model.max_short_side)
    # the depth maps are read as the views are drawn: thousands of RGB-D frames do not fit at once
    with DepthMaps(inputs.scene, [index[f.name] for f in frames[:len(frames) - n_rendered]], n_rendered) as depths:
        buf = fill_buffer(frames, encoder, options, short_side, seed=seed, keypoints=keypoints,
                          depths=depths if depths.any() else None,
                          mapping_images=len(frames) - n_rendered, device=device)
    # Held-out mapping images, unaugmented: training measures its held-out fit on them (train.validate_every).
    heldout = fill_heldout(holdout, encoder, options, short_side, seed=seed, device=device) if holdout else None
    attrs = {"short_side": short_side, "encoder_file": weights.name, "encoder_fingerprint": encoder_fingerprint(encoder)}
    write_buffer(out / BUFFER_H5, buf, **attrs)
    if heldout is not None:
        write_buffer(out / HOLDOUT_H5, heldout, **attrs)
    stats = {"cells": len(buf.features), "views": len(buf.view_image), "mapping_images": len(frames) - n_rendered,
             "rendered_images": n_rendered,
             "holdout_images": len(holdout), "holdout_cells": 0 if heldout is None else len(heldout.features),
             "rendered_buffer_views": int((buf.view_image >= len(frames) - n_rendered).sum()),
             "short_side": short_side, "feature_dim": int(buf.features.shape[1]),
             "megabytes": (out / BUFFER_H5).stat().st_size / 2**20,
             "encoder": weights.name, "keypoint_observations": len(buf.kp_id),
             "keypoints_observed": int(len(set(buf.kp_id.tolist()))), "keypoints_kept": len(buf.keypoint_xyz),
             "keypoint_observations_from_depth": int(buf.kp_from_depth.sum())}
    log.info("buffer: %d cells from %d views", stats["cells"], stats["views"])
    return stats
