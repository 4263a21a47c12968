"""Import a scene from its source format and bring every image to the working resolution."""

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


def prepare_scene(scene: Scene, out_dir: Path, working_width: int) -> dict:
    """Write resized images and scene.h5 into `out_dir` (which must be empty); return stats."""
    scene.split("train")
    scene.split("test")
    out_frames: list[Frame] = []
    depths: list[np.ndarray | None] = []
    for frame in tqdm(scene.frames, desc=f"prepare {scene.name}", unit="img"):
        image = _read_image(frame.image_path)
        h, w = image.shape[:2]
        if (w, h) != (frame.camera.width, frame.camera.height):
            raise SceneError(
                f"{frame.image_path}: image is {w}x{h} but its camera says "
                f"{frame.camera.width}x{frame.camera.height}"
            )
        ww, wh = working_size(w, h, working_width)
        if (ww, wh) != (w, h):
            image = cv2.resize(image, (ww, wh), interpolation=cv2.INTER_AREA)
        dst = out_dir / IMAGE_DIR / frame.name
        dst.parent.mkdir(parents=True, exist_ok=True)
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if dst.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(dst), image, params):
            raise SceneError(f"cannot write image {dst}")
        depth = _read_depth(frame)
        if depth is not None and depth.shape[:2] != (wh, ww):
            depth = cv2.resize(depth, (ww, wh), interpolation=cv2.INTER_NEAREST)
        depths.append(depth)
        out_frames.append(replace(frame, image_path=dst, camera=frame.camera.scaled(ww, wh), depth_path=None))
    prepared = Scene(scene.name, out_frames, scene.metric_scale, out_dir)
    write_scene_h5(out_dir / SCENE_FILE, prepared, depths)
    n_train = len(prepared.split("train"))
    stats = {
        "frames": len(out_frames),
        "train": n_train,
        "test": len(out_frames) - n_train,
        "width": out_frames[0].camera.width,
        "height": out_frames[0].camera.height,
        "has_depth": any(d is not None for d in depths),
    }
    log.info("prepared %s: %s", scene.name, stats)
    return stats
