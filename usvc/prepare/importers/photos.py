"""``images``: a folder of photos and nothing else (no poses, no calibration).

Photos are ``<root>/images/*`` when that folder exists, else ``<root>/*``, in lexicographic
order, split by ``every_nth``. Each photo gets a SIMPLE_RADIAL camera (COLMAP's default for
phone photos) with no distortion yet; its focal length is the EXIF one when the JPEG has it (a
prior that bundle adjustment refines) and 1.2 x the longer side otherwise (estimated by SfM).
Photos share a camera when their size and EXIF focal length agree (one camera per physical
camera and zoom setting): SfM then calibrates it from all of them. The prepare stage poses the frames by SfM (:mod:`usvc.sfm.posing`).

An EXIF focal length whose field of view no camera has (e.g. FocalLengthIn35mmFilm = 1: 174 deg)
is refused, naming the photo and the focal length; ``exif_focal=False`` (``usvc map --no-exif``,
``scene.exif_focal=false``) ignores every EXIF focal length. Whatever in the folder is not a
photo (a .heic, a text file, a subfolder) is listed in one warning (:func:`skipped_entries`);
hidden files (``.DS_Store``) are left out of it.
"""

from __future__ import annotations

import logging
from pathlib import Path

from usvc.core.errors import SceneError
from usvc.core.exif import exif_focal_px
from usvc.core.geometry import field_of_view_deg
from usvc.core.scene import Scene
from usvc.prepare.importers.common import (
    IMAGE_SUFFIXES,
    assign_splits,
    image_size,
    is_image,
    list_images,
    make_camera,
    make_frame,
)

log = logging.getLogger(__name__)

UNKNOWN_FOCAL_FACTOR = 1.2  # COLMAP's initial focal for an uncalibrated camera, times the longer side
# Field of view across the longer side that an EXIF focal length may imply: a 35 mm equivalent of
# about 4.8 mm (fisheye-like) to 410 mm (long telephoto). Outside it the tag is wrong, not the lens.
MIN_FOV_DEG, MAX_FOV_DEG = 5.0, 150.0
FILM_LONG_SIDE_MM = 36.0
SKIPPED_EXAMPLES = 3  # names the warning shows


def photo_folder(root: Path) -> Path:
    """Where the photos are: ``<root>/images`` when that folder exists, else ``<root>``."""
    return root / "images" if (root / "images").is_dir() else root


def skipped_entries(root: Path) -> dict[str, str]:
    """What the photo folder holds besides photos, name (relative to ``root``) -> why it is not read.
    Hidden entries (``.DS_Store``, ``.thumbnails``) are not listed."""
    folder = photo_folder(root)
    out: dict[str, str] = {}
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        if path.name.startswith(".") or is_image(path):
            continue
        rel = path.relative_to(root).as_posix()
        if path.is_dir():
            out[rel + "/"] = "a folder (subfolders are not read)"
        elif path.is_file():
            out[rel] = f"unsupported type {path.suffix.lower()}" if path.suffix else "no image extension"
        else:
            out[rel] = "unreadable (a broken or looping link?)"
    return out


def _warn_skipped(name: str, folder: Path, skipped: dict[str, str], n_photos: int) -> None:
    if not skipped:
        return
    shown = ", ".join(f"{k} ({why})" for k, why in list(skipped.items())[:SKIPPED_EXAMPLES])
    more = f" and {len(skipped) - SKIPPED_EXAMPLES} more" if len(skipped) > SKIPPED_EXAMPLES else ""
    log.warning("images %s: skipped %d of the entries in %s, read %d photos (%s only): %s%s", name, len(skipped),
                folder, n_photos, " ".join(IMAGE_SUFFIXES), shown, more)


def check_exif_focal(path: Path, focal_px: float, w: int, h: int) -> None:
    """Refuse an EXIF focal length whose field of view (across the longer side) no camera has."""
    long_side = max(w, h)
    fov = field_of_view_deg(focal_px, long_side)
    if MIN_FOV_DEG <= fov <= MAX_FOV_DEG:
        return
    f35 = focal_px * FILM_LONG_SIDE_MM / long_side
    raise SceneError(f"{path}: its EXIF focal length ({f35:.3g} mm 35 mm-equivalent, {focal_px:.4g} px at {w}x{h}) "
                     f"implies a {fov:.1f} deg field of view, outside the {MIN_FOV_DEG:g}-{MAX_FOV_DEG:g} deg of a "
                     "camera: the EXIF is wrong; ignore EXIF focal lengths with `usvc map --no-exif` "
                     "(scene.exif_focal=false)")


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None,
         exif_focal: bool = True) -> Scene:
    folder = photo_folder(root)
    images = list_images(folder)
    _warn_skipped(name, folder, skipped_entries(root), len(images))
    if not images:
        raise SceneError(f"scene {name!r}: no photos (.jpg .png ...) in {folder}")
    splits = assign_splits(len(images), split_rule, split_n, None, name, "images")
    frames, with_exif = [], 0
    for img, split in zip(images, splits):
        where = str(img)
        w, h = image_size(img)
        focal = exif_focal_px(img) if exif_focal else None
        if focal is not None:
            check_exif_focal(img, focal, w, h)
        with_exif += focal is not None
        f = focal if focal is not None else UNKNOWN_FOCAL_FACTOR * max(w, h)
        camera = make_camera(where, "SIMPLE_RADIAL", w, h, (round(f, 6), w / 2.0, h / 2.0, 0.0))
        frame_name = img.relative_to(root).as_posix()
        frames.append(make_frame(where, name=frame_name, image_path=img, camera=camera, split=split,
                                 focal_known=focal is not None))
    log.info("images %s: %d photos in %s, %d with an EXIF focal length%s", name, len(frames), folder, with_exif,
             "" if exif_focal else " (EXIF focal lengths ignored)")
    return Scene(name=name, frames=frames, metric_scale=metric_scale, root=root)
