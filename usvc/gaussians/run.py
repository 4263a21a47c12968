"""The gaussians step: fit a 3D Gaussian splatting model to the mapping images, initialised from
the SfM points -> splat.ply, a held-out render beside its photo, PSNR/SSIM on held-out images."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from usvc.core.artifact_names import SPLAT_CHECK_PNG, SPLAT_PLY
from usvc.core.scene_file import read_scene_h5
from usvc.gaussians.fit import FitImage, fit_gaussians, load_fit_images, split_holdout
from usvc.gaussians.options import GaussiansOptions
from usvc.sfm.tracks_file import Tracks, read_tracks
from usvc.splat.gaussians import Gaussians, from_points
from usvc.splat.ply_file import read_splat_ply, write_splat_ply
from usvc.splat.rasterize import render

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    tracks: Path  # the SfM model (sfm/tracks.h5): one initial Gaussian per point
    scene: Path  # the prepared scene (prepared/scene.h5): the mapping images


def initial_gaussians(tracks: Tracks, sh_degree: int, initial_opacity: float) -> Gaussians:
    """One Gaussian per SfM point, coloured by the point's observations (COLMAP's mean colour)."""
    return from_points(tracks.xyz, tracks.rgb, sh_degree, initial_opacity)


@torch.no_grad()
def ply_reload_difference(ply: Path, model: Gaussians, image: FitImage, tile: int) -> float:
    """Largest pixel difference between a render of `model` and of the PLY written from it."""
    a = render(model, image.view, tile=tile).rgb
    b = render(read_splat_ply(ply), image.view, tile=tile).rgb
    return float(np.abs((a - b).numpy()).max())


def run(inputs: Inputs, out: Path, options: GaussiansOptions, *, device: str = "cpu") -> dict:
    """Fit the model on `device` and write it into `out`; returns its figures."""
    tracks = read_tracks(inputs.tracks)
    images = load_fit_images(read_scene_h5(inputs.scene).split("train"), options.width)
    init = initial_gaussians(tracks, options.sh_degree, options.initial_opacity)
    log.info("gaussians: fitting %d initial Gaussians to %d images at %dx%d, %d iterations", len(init), len(images),
             images[0].view.width, images[0].view.height, options.iterations)
    result = fit_gaussians(init, images, options, device=device)
    _, held = split_holdout(images, options.holdout_every)
    check = held[0] if held else images[0]
    write_splat_ply(out / SPLAT_PLY, result.gaussians)
    reload_diff = ply_reload_difference(out / SPLAT_PLY, result.gaussians, check, options.tile)
    with torch.no_grad():
        pred = render(result.gaussians, check.view, tile=options.tile).rgb.clamp(0, 1).numpy()
    side = np.concatenate([pred, check.rgb.numpy()], axis=1)
    cv2.imwrite(str(out / SPLAT_CHECK_PNG), (side[..., ::-1] * 255).round().astype(np.uint8))
    stats = {"computed": True, **result.metrics,
             "ply_megabytes": (out / SPLAT_PLY).stat().st_size / 2**20, "ply_reload_max_abs_diff": reload_diff,
             "seed": options.seed}
    log.info("gaussians: %d Gaussians, held-out PSNR %.2f dB, SSIM %.3f, fit %.0f s", stats["gaussians"],
             stats["heldout_psnr"] or float("nan"), stats["heldout_ssim"] or float("nan"), stats["fit_seconds"])
    return stats
