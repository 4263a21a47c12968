"""Options of the 3D Gaussian splatting fit (the `gaussians` config group; 3DGS, Kerbl et al. 2023,
scaled down for a CPU): learning rates, spherical-harmonic schedule and adaptive density control."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import in_range, non_negative, positive


@dataclass
class GaussiansOptions:
    """3DGS fit (stages/gaussians.py). The defaults are sized for the miniature scene on a 2-core CPU
    (about 2 minutes); the reference 3DGS schedule is gaussians=reference (GPU-sized)."""

    iterations: int = 400  # optimiser steps, one image each
    width: int = 160  # fit and evaluation width, px; 0 = the prepared images' width
    sh_degree: int = 3  # spherical-harmonic degree of the colours (0..3)
    sh_increase_every: int = 100  # one more SH band every this many iterations
    ssim_weight: float = 0.2  # L = (1 - w) L1 + w D-SSIM
    lr_means: float = 1.6e-4  # learning rate of the positions, times the scene extent, decayed exponentially ...
    lr_means_final: float = 1.6e-6  # ... to this by the last iteration
    lr_sh_dc: float = 2.5e-3  # learning rate of the base colour
    lr_sh_rest: float = 1.25e-4  # learning rate of the higher SH bands
    lr_opacity: float = 0.05  # learning rate of the opacity logits
    lr_scales: float = 5e-3  # learning rate of the log scales
    lr_quats: float = 1e-3  # learning rate of the rotations
    densify_from: int = 100  # adaptive density control starts at this iteration ...
    densify_until: int = 300  # ... and stops after this one
    densify_every: int = 50  # densify and prune every this many iterations
    opacity_reset_every: int = 200  # reset opacities every this many iterations; 0 = never
    densify_grad_threshold: float = 2e-4  # clone/split where the mean view-space gradient norm (NDC units, as the reference) reaches this
    percent_dense: float = 0.01  # clone below, split above this fraction of the scene extent
    min_opacity: float = 0.005  # prune Gaussians more transparent than this
    max_screen_radius: float = 0.0  # prune Gaussians larger than this on screen, px; 0 = off
    max_world_scale: float = 0.1  # prune Gaussians larger than this fraction of the extent (after the first reset)
    max_gaussians: int = 20000  # cap on their number: CPU time and memory stay bounded
    initial_opacity: float = 0.1  # opacity of the Gaussians initialised from the SfM points
    holdout_every: int = 8  # every n-th mapping image is held out for PSNR/SSIM; 0 = none
    tile: int = 8  # rasteriser tile, px
    seed: int = 0  # fit seed (image order)

    def problems(self) -> list[str]:
        out = positive(self, "iterations", "sh_increase_every", "lr_means", "lr_means_final", "densify_every",
                       "densify_grad_threshold", "percent_dense", "max_world_scale", "max_gaussians",
                       "initial_opacity", "tile")
        out += non_negative(self, "width", "densify_from", "densify_until", "opacity_reset_every", "holdout_every",
                            "max_screen_radius")
        out += in_range(self, "sh_degree", 0, 3) + in_range(self, "ssim_weight", 0.0, 1.0)
        if not 0 < self.initial_opacity < 1:
            out.append(f"initial_opacity={self.initial_opacity!r} must be in (0, 1)")
        return out
