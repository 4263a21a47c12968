"""COLMAP sparse model (``cameras/images/points3D`` as ``.bin`` or ``.txt``), read by pycolmap.

COLMAP already uses the canonical conventions (world-to-camera, OpenCV axes, pixel centre at
0.5), so poses and camera parameters pass through unchanged. Only registered images are
imported. COLMAP has no train/test split, so only ``every_nth`` applies.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.errors import SceneError
from usvc.core.scene import CAMERA_MODELS, Camera, Scene
from usvc.prepare.importers.common import (
    assign_splits,
    make_camera,
    make_frame,
    natural_key,
)

log = logging.getLogger(__name__)


def _is_model_dir(d: Path) -> bool:
    return (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file()


def find_model_dir(root: Path) -> Path:
    """The model folder: ``root`` itself, ``root/sparse/0`` or ``root/sparse``."""
    for d in (root, root / "sparse" / "0", root / "sparse"):
        if _is_model_dir(d):
            return d
    raise SceneError(f"no COLMAP model (cameras.bin or cameras.txt) in {root}, {root}/sparse/0 or {root}/sparse")


def find_images_dir(root: Path, model_dir: Path) -> Path:
    """The ``images/`` folder next to the model: the scene root or a parent of the model."""
    for d in (root, model_dir, model_dir.parent, model_dir.parent.parent):
        if (d / "images").is_dir():
            return d / "images"
    raise SceneError(f"no images/ folder found for the COLMAP model in {model_dir}")


def _camera(cam: pycolmap.Camera, where: str) -> Camera:
    model = cam.model.name
    if model not in CAMERA_MODELS:
        raise SceneError(f"{where}: camera {cam.camera_id} has unsupported model {model}; supported: {sorted(CAMERA_MODELS)}")
    return make_camera(where, model, cam.width, cam.height, np.asarray(cam.params, dtype=np.float64))


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import the model under ``root`` (model folder or scene root with ``sparse/`` and ``images/``)."""
    model_dir = find_model_dir(root)
    images_dir = find_images_dir(root, model_dir)
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (ValueError, RuntimeError, OSError) as e:
        raise SceneError(f"{model_dir}: unreadable COLMAP model ({e})") from None
    images = [im for im in rec.images.values() if im.has_pose]
    skipped = rec.num_images() - len(images)
    if skipped:
        log.info("colmap %s: %d unregistered images skipped", name, skipped)
    images.sort(key=lambda im: natural_key(im.name))
    splits = assign_splits(len(images), split_rule, split_n, None, name, "colmap")
    cameras: dict[int, Camera] = {}
    frames = []
    scene_root = images_dir.parent
    for im, split in zip(images, splits):
        where = f"{model_dir} image {im.name!r}"
        if im.camera_id not in cameras:
            cameras[im.camera_id] = _camera(rec.cameras[im.camera_id], str(model_dir))
        pose = im.cam_from_world()
        frames.append(
            make_frame(
                where,
                name=(images_dir / im.name).relative_to(scene_root).as_posix(),
                image_path=images_dir / im.name,
                camera=cameras[im.camera_id],
                split=split,
                R=np.asarray(pose.rotation.matrix(), dtype=np.float64),
                t=np.asarray(pose.translation, dtype=np.float64),
            )
        )
    log.info("colmap %s: %d frames from %s", name, len(frames), model_dir)
    return Scene(name=name, frames=frames, metric_scale=metric_scale, root=scene_root)
