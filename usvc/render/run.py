"""The render step: novel views around keypoint clusters rendered from the 3DGS model, with the
keypoints each view sees -> render.h5 and the rendered images."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from usvc.core.artifact_names import RENDER_H5
from usvc.core.scene_file import read_scene_h5
from usvc.keypoints.keypoints_file import read_scene_keypoints
from usvc.render.novel_views import render_novel_views
from usvc.render.options import RenderOptions
from usvc.render.views_file import write_rendered_views
from usvc.splat.ply_file import read_splat_ply

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    splat: Path  # the Gaussian splatting model (gaussians/splat.ply)
    scene: Path  # the prepared scene (prepared/scene.h5): the mapping cameras the views start from
    keypoints: Path  # the kept keypoints (keypoints/keypoints.h5)


def run(inputs: Inputs, out: Path, options: RenderOptions, *, tile: int, device: str = "cpu") -> dict:
    """Render the views on `device` into `out` (rasteriser tiles of `tile` pixels, as the fit);
    returns their figures."""
    model = read_splat_ply(inputs.splat)
    frames = read_scene_h5(inputs.scene).split("train")
    keypoints = read_scene_keypoints(inputs.keypoints)
    views, stats = render_novel_views(model, frames, keypoints, options, tile=tile, device=device)
    write_rendered_views(out / RENDER_H5, views)
    stats.update({"computed": True, "seed": options.seed, "width": int(views[0].rgb.shape[1]),
                  "height": int(views[0].rgb.shape[0])})
    log.info("render: %d views, %.0f visible keypoints per view, %.1f deg from the source on average",
             stats["views"], stats["mean_visible_keypoints"], stats["mean_angle_deg"])
    return stats
