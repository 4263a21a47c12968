"""``images``: a folder of photos and nothing else (no poses, no calibration).

Photos are ``<root>/images/*`` when that folder exists, else ``<root>/*``, in lexicographic
order, split by ``every_nth``. Each photo gets a SIMPLE_RADIAL camera (COLMAP's default for
phone photos) with no distortion yet; its focal length is the EXIF one when the JPEG has it (a
prior that bundle adjustment refines) and 1.2 x the longer side otherwise (estimated by SfM).
Photos share a camera when their size and EXIF focal length agree (one camera per physical
camera and zoom setting): SfM then calibrates it from all of them. The prepare stage poses the frames by SfM (:mod:`usvc.sfm.posing`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from usvc.core.errors import SceneError
from usvc.core.exif import exif_focal_px
from usvc.core.scene import Scene
from usvc.prepare.importers.common import (
    assign_splits,
    image_size,
    list_images,
    make_camera,
    make_frame,
)

log = logging.getLogger(__name__)

UNKNOWN_FOCAL_FACTOR = 1.2  # COLMAP's initial focal for an uncalibrated camera, times the longer side


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    folder = root / "images" if (root / "images").is_dir() else root
    images = list_images(folder)
    if not images:
        raise SceneError(f"scene {name!r}: no photos (.jpg .png ...) in {folder}")
    splits = assign_splits(len(images), split_rule, split_n, None, name, "images")
    frames, with_exif = [], 0
    for img, split in zip(images, splits):
        where = str(img)
        w, h = image_size(img)
        focal = exif_focal_px(img)
        with_exif += focal is not None
        f = focal if focal is not None else UNKNOWN_FOCAL_FACTOR * max(w, h)
        camera = make_camera(where, "SIMPLE_RADIAL", w, h, (round(f, 6), w / 2.0, h / 2.0, 0.0))
        frame_name = img.relative_to(root).as_posix()
        frames.append(make_frame(where, name=frame_name, image_path=img, camera=camera, split=split,
                                 focal_known=focal is not None))
    log.info("images %s: %d photos in %s, %d with an EXIF focal length", name, len(frames), folder, with_exif)
    return Scene(name=name, frames=frames, metric_scale=metric_scale, root=root)
