"""SfM initialisation and the PLY reload check of the gaussians stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from usvc.gaussians.fit import FitImage
from usvc.sfm.tracks import Tracks
from usvc.splat.gaussians import Gaussians, from_points
from usvc.splat.ply_file import read_splat_ply
from usvc.splat.rasterize import render


def initial_gaussians(tracks: Tracks, sh_degree: int, initial_opacity: float) -> Gaussians:
    """One Gaussian per SfM point, coloured by the point's observations (COLMAP's mean colour)."""
    return from_points(tracks.xyz, tracks.rgb, sh_degree, initial_opacity)


@torch.no_grad()
def ply_reload_difference(ply: Path, model: Gaussians, image: FitImage, tile: int) -> float:
    """Largest pixel difference between a render of `model` and of the PLY written from it."""
    a = render(model, image.view, tile=tile).rgb
    b = render(read_splat_ply(ply), image.view, tile=tile).rgb
    return float(np.abs((a - b).numpy()).max())
