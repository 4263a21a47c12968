"""LLFF layout: ``images/`` plus ``poses_bounds.npy`` (N, 17), as written by LLFF's imgs2poses.

Each row is a 3x5 matrix (row-major) followed by near/far bounds. The 3x5 matrix holds a
camera-to-world rotation whose columns are the camera's (down, right, backwards) axes, the
camera centre, and (height, width, focal) at the resolution the poses were estimated at.
Rows follow the *lexicographic* order of the image file names (``IMG_10`` before ``IMG_2``).
LLFF has no train/test split of its own: the NeRF convention is every 8th image as a query.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.scene import Frame, Scene
from usvc.prepare.importers.common import (
    assign_splits,
    image_size,
    list_images,
    make_camera,
    make_frame,
    world_to_cam_from_cam_to_world,
)

log = logging.getLogger(__name__)


def _read_poses_bounds(path: Path) -> np.ndarray:
    if not path.is_file():
        raise SceneError(f"missing pose file {path}")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise SceneError(f"{path}: unreadable pose file ({e})") from None
    if not isinstance(arr, np.ndarray):
        raise SceneError(f"{path}: expected one .npy array, found an .npz archive")
    if arr.ndim != 2 or arr.shape[1] != 17 or not np.issubdtype(arr.dtype, np.number):
        raise SceneError(f"{path}: expected a numeric (N, 17) array, got {arr.dtype} {arr.shape}")
    return arr.astype(np.float64)


def _shared_size(images: list[Path]) -> tuple[int, int]:
    """All LLFF images share one size, since one (h, w, f) rescaling is applied to every row."""
    size = image_size(images[0])
    for p in images[1:]:
        other = image_size(p)
        if other != size:
            raise SceneError(
                f"{p}: image size {other[0]}x{other[1]} differs from {images[0].name} ({size[0]}x{size[1]})"
            )
    return size


MAX_ASPECT_CHANGE = 0.01  # resizing rounds sizes to whole pixels; a crop changes the aspect more


def row_to_frame(row: np.ndarray, where: str, image: Path, name: str, split: str, size: tuple[int, int]) -> Frame:
    """One poses_bounds row to a canonical frame: reorder axes, invert, rescale the focal."""
    m = row[:15].reshape(3, 5)
    h, w, f = (float(v) for v in m[:, 4])
    if not all(np.isfinite(v) and v > 0 for v in (h, w, f)):
        raise SceneError(f"{where}: (height, width, focal) must be positive and finite, got ({h}, {w}, {f})")
    R_llff = m[:, :3]
    # (down, right, backwards) -> (right, down, forward)
    R_cam_to_world = np.stack([R_llff[:, 1], R_llff[:, 0], -R_llff[:, 2]], axis=1)
    R, t = world_to_cam_from_cam_to_world(R_cam_to_world, m[:, 3], where)
    W, H = size
    stretch = (W / w) / (H / h)
    if abs(stretch - 1) > MAX_ASPECT_CHANGE:
        raise SceneError(
            f"{where}: the images are {W}x{H} but the poses were estimated on {w:g}x{h:g} images, another aspect "
            f"ratio ({100 * (stretch - 1):+.1f} %): cropped images? LLFF's focal length holds only for the same "
            "picture scaled, so crop-free images (or poses estimated on these) are needed")
    cam = make_camera(where, "PINHOLE", W, H, (f * W / w, f * H / h, W / 2.0, H / 2.0))
    return make_frame(where, name=name, image_path=image, camera=cam, split=split, R=R, t=t)


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import an LLFF scene; ``root`` holds ``images/`` and ``poses_bounds.npy``."""
    pose_file = root / "poses_bounds.npy"
    arr = _read_poses_bounds(pose_file)
    images = list_images(root / "images")
    if len(images) != arr.shape[0]:
        raise SceneError(
            f"{pose_file}: {arr.shape[0]} pose rows but {len(images)} images in {root / 'images'}"
        )
    if not images:
        raise SceneError(f"scene {name!r}: no images in {root / 'images'}")
    splits = assign_splits(len(images), split_rule, split_n, None, name, "llff")
    size = _shared_size(images)
    frames = [
        row_to_frame(arr[i], f"{pose_file} row {i}", img, f"images/{img.name}", splits[i], size)
        for i, img in enumerate(images)
    ]
    log.info("llff %s: %d frames, images %dx%d", name, len(frames), *size)
    return Scene(name=name, frames=frames, metric_scale=metric_scale, root=root)
