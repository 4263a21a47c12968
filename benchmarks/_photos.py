"""Query photos of a prepared scene for the query-speed benchmarks, at their own size or at a given
one: cropped about the centre to the given aspect ratio first, then resized, so the pixels stay
square (a 544x960 photo resized straight to 480x640 would be stretched by 1.32, which the
relocalizer warns about, and would not be a photo any camera takes). The intrinsics follow the crop
and the resize."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from usvc.core.images import read_image_bgr
from usvc.core.scene_file import read_scene_h5
from usvc.pipeline.paths import ScenePaths


def at_size(rgb: np.ndarray, intrinsics: tuple[float, float, float, float],
            size: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """`rgb` cropped about its centre to the aspect ratio of `size` (W, H; turned for a portrait
    photo), then resized to it; (fx, fy, cx, cy) (COLMAP's pixel convention) moved and scaled with it."""
    fx, fy, cx, cy = intrinsics
    height, width = rgb.shape[:2]
    w, h = size if width >= height else size[::-1]
    if width * h > height * w:  # wider than the target: keep the full height
        cw, ch = int(round(height * w / h)), height
    else:
        cw, ch = width, int(round(width * h / w))
    x0, y0 = (width - cw) // 2, (height - ch) // 2
    crop = rgb[y0:y0 + ch, x0:x0 + cw]
    sx, sy = w / cw, h / ch
    out = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR)
    return out, (fx * sx, fy * sy, (cx - x0) * sx, (cy - y0) * sy)


def query_photos(scene_dir: Path, size: tuple[int, int] | None) -> list[tuple[np.ndarray, tuple]]:
    """(RGB array, (fx, fy, cx, cy)) of every query photo of the scene, at `size` when given."""
    out = []
    for f in read_scene_h5(ScenePaths.of_scene_dir(scene_dir).scene_file).split("test"):
        rgb = cv2.cvtColor(read_image_bgr(f.image_path), cv2.COLOR_BGR2RGB)
        (fx, fy), (cx, cy) = f.camera.focal, f.camera.principal_point
        intrinsics = (fx, fy, cx, cy)
        if size is not None:
            rgb, intrinsics = at_size(rgb, intrinsics, size)
        out.append((rgb, intrinsics))
    return out
