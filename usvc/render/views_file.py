"""The render stage's artifact: PNG images (so the buffer reads them like mapping images) and
render.h5 with each view's pose, intrinsics, source image, rendered depth and keypoint observations."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.core.scene import Camera, Frame
from usvc.core.scene_file import IMAGE_DIR


@dataclass
class NovelView:
    """One rendered view, as render.h5 and its PNG store it; `R`, `t` are world-to-camera."""

    source: str  # the mapping image it was perturbed from
    R: np.ndarray  # (3, 3) world-to-camera
    t: np.ndarray  # (3,)
    K: np.ndarray  # (3, 3)
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, 0 where nothing was rendered
    keypoint_ids: np.ndarray  # (n,) visible kept keypoints
    keypoint_uv: np.ndarray  # (n, 2) their projections, COLMAP pixel coordinates
    angle_deg: float  # rotation from the source pose
    translation: float  # camera-centre distance from the source pose, scene units


RENDER_FORMAT, RENDER_VERSION = "usvc-render", 1
_PIXELS = "pixel centres at integer+0.5 (COLMAP), x right, y down"
# Every dataset of render.h5 with its attributes; docs/artifacts.md lists the same. Row i of the
# per-view datasets is images/<iiii>.png.
RENDER_SCHEMA: dict[str, Field] = {
    "R": Field("1", "world-to-camera rotation of the rendered view: x_cam = R x_world + t, OpenCV camera axes "
                    "(x right, y down, z forward)", "world->camera"),
    "t": Field("scene units", "world-to-camera translation of the rendered view: x_cam = R x_world + t", "camera"),
    "K": Field("px", f"intrinsic matrix of the rendered view; {_PIXELS}", "camera->image"),
    "size": Field("px", "width, height of the rendered image", "image"),
    "source": Field("1", "mapping image (prepared name, fixed-length UTF-8 bytes) whose pose the view was "
                         "perturbed from"),
    "angle_deg": Field("deg", "rotation angle between the view and its source pose"),
    "depth": Field("scene units", "rendered expected depth (alpha-weighted z along the optical axis) per pixel, "
                                  "0 where nothing was rendered (fp16)", "camera"),
    "obs/offset": Field("1", "CSR offsets: the keypoint observations of view i are obs/keypoint, obs/uv rows "
                             "offset[i]:offset[i+1]; length views + 1"),
    "obs/keypoint": Field("1", "keypoint index: row of keypoints.h5 keypoints/* (not a COLMAP id)"),
    "obs/uv": Field("px", f"projection of the visible keypoint into the rendered view; {_PIXELS}", "image"),
}


def write_rendered_views(path: Path, views: list[NovelView]) -> None:
    """render.h5 at `path`, and the views' images in IMAGE_DIR beside it."""
    path = Path(path)
    images = path.parent / IMAGE_DIR
    images.mkdir(parents=True, exist_ok=True)
    offsets = np.cumsum([0] + [len(v.keypoint_ids) for v in views])
    with write_h5(path, RENDER_SCHEMA, RENDER_FORMAT, RENDER_VERSION) as h5:
        h5["R"] = np.stack([v.R for v in views])
        h5["t"] = np.stack([v.t for v in views])
        h5["K"] = np.stack([v.K for v in views])
        h5["size"] = np.array([[v.rgb.shape[1], v.rgb.shape[0]] for v in views], dtype=np.int32)
        h5["source"] = np.array([v.source.encode() for v in views])
        h5["angle_deg"] = np.array([v.angle_deg for v in views])
        h5.create_dataset("depth", data=np.stack([v.depth for v in views]).astype(np.float16), compression="gzip")
        h5["obs/offset"] = offsets
        h5["obs/keypoint"] = np.concatenate([v.keypoint_ids for v in views]).astype(np.int32)
        h5["obs/uv"] = np.concatenate([v.keypoint_uv for v in views]).astype(np.float32)
    for i, v in enumerate(views):
        if not cv2.imwrite(str(images / f"{i:04d}.png"), v.rgb[..., ::-1]):
            raise UsvcError(f"could not write {images / f'{i:04d}.png'}")


def read_rendered_views(path: Path) -> tuple[list[Frame], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The views of render.h5 `path` as mapping frames (names 'render/NNNN.png', images in IMAGE_DIR
    beside it), and their keypoint observations keyed by those names, in the form
    `SceneKeypoints.by_image` takes."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"rendered views not found: {path} (run the render stage, or use a method without "
                        "rendered views)")
    frames, obs = [], {}
    with read_h5(path, "rendered views") as h5:
        R, t, K, size = h5["R"][()], h5["t"][()], h5["K"][()], h5["size"][()]
        off, kp, uv = h5["obs/offset"][()], h5["obs/keypoint"][()], h5["obs/uv"][()].astype(np.float64)
    for i in range(len(R)):
        image = path.parent / IMAGE_DIR / f"{i:04d}.png"
        if not image.is_file():
            raise UsvcError(f"rendered image missing: {image}")
        name = f"render/{i:04d}.png"
        cam = Camera("PINHOLE", int(size[i, 0]), int(size[i, 1]), (K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]))
        frames.append(Frame(name=name, image_path=image, camera=cam, split="train", R=R[i], t=t[i]))
        obs[name] = (kp[off[i]:off[i + 1]].astype(np.int64), uv[off[i]:off[i + 1]])
    return frames, obs
