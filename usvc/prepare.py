"""Import a scene, undistort every image to a PINHOLE camera, and resize it to the working width.

Undistortion happens here, once, at the source resolution (``usvc.undistort``), before resizing:
every later stage (SfM, buffer, Gaussian splatting, relocalization, metrics) sees pinhole images
only. Poses are unchanged by undistortion, so metrics still score against the imported poses.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from usvc.errors import SceneError
from usvc.scene import Frame, Scene
from usvc.scene_io import IMAGE_DIR, SCENE_FILE, write_scene_h5
from usvc.undistort import undistort

log = logging.getLogger(__name__)


def working_size(width: int, height: int, working_width: int) -> tuple[int, int]:
    """Size after resizing to `working_width` (0 keeps it), preserving the aspect ratio."""
    if working_width == 0 or working_width == width:
        return width, height
    return working_width, max(1, round(height * working_width / width))


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise SceneError(f"cannot read image {path} (missing, empty or not an image)")
    return image


def _read_depth(frame: Frame) -> np.ndarray | None:
    if frame.depth_path is None or not Path(frame.depth_path).is_file():
        return None
    raw = cv2.imread(str(frame.depth_path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SceneError(f"cannot read depth map {frame.depth_path}")
    return raw.astype(np.float32) * np.float32(frame.depth_scale)


def prepare_scene(scene: Scene, out_dir: Path, working_width: int, undistort_fov: str = "crop") -> dict:
    """Write undistorted, resized images and scene.h5 into `out_dir` (which must be empty).

    `undistort_fov` is ``crop`` (no black borders) or ``full`` (every source pixel kept); see
    :mod:`usvc.undistort`. Returns summary figures for the stage's metrics file.
    """
    scene.split("train")
    scene.split("test")
    out_frames: list[Frame] = []
    depths: list[np.ndarray | None] = []
    for frame in tqdm(scene.frames, desc=f"prepare {scene.name}", unit="img"):
        image, camera = undistort(_read_image(frame.image_path), frame.camera, undistort_fov,
                                  where=str(frame.image_path))
        depth = _read_depth(frame)
        if depth is not None and frame.camera.has_distortion:
            depth = cv2.resize(depth, (frame.camera.width, frame.camera.height), interpolation=cv2.INTER_NEAREST)
            depth, _ = undistort(depth, frame.camera, undistort_fov, where=str(frame.depth_path), nearest=True)
        h, w = image.shape[:2]
        ww, wh = working_size(w, h, working_width)
        if (ww, wh) != (w, h):
            image = cv2.resize(image, (ww, wh), interpolation=cv2.INTER_AREA)
        dst = out_dir / IMAGE_DIR / frame.name
        dst.parent.mkdir(parents=True, exist_ok=True)
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if dst.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(dst), image, params):
            raise SceneError(f"cannot write image {dst}")
        if depth is not None and depth.shape[:2] != (wh, ww):
            depth = cv2.resize(depth, (ww, wh), interpolation=cv2.INTER_NEAREST)
        depths.append(depth)
        out_frames.append(replace(frame, image_path=dst, camera=camera.scaled(ww, wh), depth_path=None))
    prepared = Scene(scene.name, out_frames, scene.metric_scale, out_dir)
    write_scene_h5(out_dir / SCENE_FILE, prepared, depths, source_cameras=[f.camera for f in scene.frames])
    n_train = len(prepared.split("train"))
    stats = {
        "frames": len(out_frames),
        "train": n_train,
        "test": len(out_frames) - n_train,
        "width": out_frames[0].camera.width,
        "height": out_frames[0].camera.height,
        "has_depth": any(d is not None for d in depths),
        "undistorted": sum(f.camera.has_distortion for f in scene.frames),
        "source_camera_models": sorted({f.camera.model for f in scene.frames}),
        "undistort_fov": undistort_fov,
    }
    log.info("prepared %s: %s", scene.name, stats)
    return stats
