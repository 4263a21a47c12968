"""Options of a scene (the `scene` config group): where its photos are, their layout and split."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from usvc.core.options import one_of, positive

FORMATS = ("llff", "transforms", "colmap", "ace", "7scenes", "cambridge", "images")
SPLIT_RULES = ("given", "every_nth")
UNDISTORT_FOV = ("crop", "full")
# working_width bounds (0 keeps the size): below MIN, SfM and the network have nothing to work on (and
# rounding the height makes a radial camera anisotropic); above MAX, no camera's photos are that wide.
MIN_WORKING_WIDTH, MAX_WORKING_WIDTH = 64, 16384


@dataclass
class SceneOptions:
    name: str = "???"  # the scene's name: data/<name>/, results/<name>/
    format: str = "???"  # input layout: llff | transforms | colmap | ace | 7scenes | cambridge | images
    path: str = "???"  # folder holding the scene in that layout
    split: str = "???"  # given (the format's own mapping/query split) | every_nth
    split_n: int = 8  # split=every_nth: every n-th image is a query
    metric_scale: Optional[float] = None  # metres per scene unit; null = unknown (errors in % of median depth)
    working_width: int = 640  # images are resized to this width before anything else; 0 = keep
    undistort_fov: str = "crop"  # distorted cameras become pinhole: crop (no black border) | full (every pixel)
    generated: bool = False  # produced by the generate stage (the bundled miniature scene)
    exif_focal: bool = True  # format images (unposed photos): EXIF focal lengths are SfM's prior (false, or `usvc map --no-exif`: ignored, estimated by SfM)

    def problems(self) -> list[str]:
        out = one_of(self, "format", FORMATS) + one_of(self, "split", SPLIT_RULES)
        out += one_of(self, "undistort_fov", UNDISTORT_FOV) + positive(self, "split_n")
        if self.working_width != 0 and not MIN_WORKING_WIDTH <= self.working_width <= MAX_WORKING_WIDTH:
            out.append(f"working_width={self.working_width!r} must be 0 (keep the size) or in "
                       f"[{MIN_WORKING_WIDTH}, {MAX_WORKING_WIDTH}] px")
        if self.metric_scale is not None and not (math.isfinite(self.metric_scale) and self.metric_scale > 0):
            out.append(f"metric_scale={self.metric_scale!r} must be finite and > 0, or null")
        return out
