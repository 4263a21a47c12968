"""Options of the training buffer (the `buffer` config group): encoder features of augmented
mapping views, sampled on the cell grid, plus the keypoint tuples each view sees."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import non_negative, one_of, ordered, positive
from usvc.core.precision import PRECISIONS


@dataclass
class BufferOptions:
    """Training buffer (ACE-style augmentation): encoder features of augmented mapping views, sampled
    on the cell grid, plus the keypoint tuples each view sees. Sizes are in cells (one feature per
    8x8 px)."""

    size: int = 0  # cells (feature vectors with their pixel and view); 0 = sized by the scene (cells_for): cells_per_image x mapping photos, within [min_size, max_size]
    cells_per_image: int = 4096  # size=0: cells per mapping photo ...
    min_size: int = 262144  # ... but at least this many (small scenes: mini's 60 photos get 262,144 cells) ...
    max_size: int = 1048576  # ... and at most this many (about 1 GiB of buffer on disk and in memory: 256 photos and more)
    samples_per_image: int = 1024  # cells drawn from each augmented view
    short_side: int = 0  # working short side the map is trained and queried at; 0 = the prepared images', at most model.max_short_side
    scale_min: float = 0.6667  # random rescaling of each view, lower bound
    scale_max: float = 1.5  # random rescaling of each view, upper bound
    max_rotation_deg: float = 15.0  # random in-plane rotation of each view, at most this (degrees)
    brightness_min: float = 0.9  # random brightness factor, lower bound
    brightness_max: float = 1.1  # random brightness factor, upper bound
    contrast_min: float = 0.9  # random contrast factor, lower bound
    contrast_max: float = 1.1  # random contrast factor, upper bound
    keypoint_obs_per_view: int = 1024  # keypoint tuples (k, d_k, R_i, t_i, u_obs) kept per augmented view; 0 = all
    depth_visibility_tol: float = 0.05  # depth maps only: a keypoint off its track counts as seen where |depth - z| < tol * z
    rendered_views: bool = False  # add the render stage's Gaussian-splatting views (set by method=multiview_gs)
    holdout_every: int = 0  # withhold every k-th mapping image from training (a validation split: holdout.h5 for train.validate_every, `benchmarks.accuracy diagnose-map`); 0 = none
    precision: str = "auto"  # the encoder's products: auto (bf16 where native and faster, else fp32) | bf16 | fp32

    def problems(self) -> list[str]:
        out = positive(self, "cells_per_image", "min_size", "max_size", "samples_per_image", "scale_min", "scale_max", "brightness_min",
                       "contrast_min", "depth_visibility_tol")
        out += one_of(self, "precision", PRECISIONS)
        out += non_negative(self, "size", "short_side", "keypoint_obs_per_view", "holdout_every", "max_rotation_deg")
        for low, high in (("min_size", "max_size"), ("scale_min", "scale_max"), ("brightness_min", "brightness_max"),
                          ("contrast_min", "contrast_max")):
            out += ordered(self, low, high)
        return out

    def cells_for(self, mapping_images: int) -> int:
        """Cells of the buffer for a scene of `mapping_images` photos: `size` when set, else a budget
        that grows with the scene as ACE's does (`cells_per_image` each, within [min_size, max_size])."""
        if self.size:
            return self.size
        return min(self.max_size, max(self.min_size, self.cells_per_image * mapping_images))
