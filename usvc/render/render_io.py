"""The render stage's artifact: PNG images (so the buffer reads them like mapping images) and
render.h5 with each view's pose, intrinsics, source image, rendered depth and keypoint observations."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from usvc.core.errors import UsvcError
from usvc.core.h5io import read_h5, write_h5
from usvc.core.scene import Camera, Frame
from usvc.render.novel_views import NovelView


def write_rendered_views(out_dir: Path, views: list[NovelView]) -> None:
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    offsets = np.cumsum([0] + [len(v.keypoint_ids) for v in views])
    with write_h5(out_dir / "render.h5") as h5:
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
        if not cv2.imwrite(str(out_dir / "images" / f"{i:04d}.png"), v.rgb[..., ::-1]):
            raise UsvcError(f"could not write {out_dir / 'images' / f'{i:04d}.png'}")


def read_rendered_views(render_dir: Path) -> tuple[list[Frame], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Rendered views as mapping frames (names 'render/NNNN.png'), and their keypoint observations
    keyed by those names, in the form `SceneKeypoints.by_image` takes."""
    path = Path(render_dir) / "render.h5"
    if not path.is_file():
        raise UsvcError(f"rendered views not found: {path} (run the render stage, or use a method without "
                        "rendered views)")
    frames, obs = [], {}
    with read_h5(path, "rendered views") as h5:
        R, t, K, size = h5["R"][()], h5["t"][()], h5["K"][()], h5["size"][()]
        off, kp, uv = h5["obs/offset"][()], h5["obs/keypoint"][()], h5["obs/uv"][()].astype(np.float64)
    for i in range(len(R)):
        image = Path(render_dir) / "images" / f"{i:04d}.png"
        if not image.is_file():
            raise UsvcError(f"rendered image missing: {image}")
        name = f"render/{i:04d}.png"
        cam = Camera("PINHOLE", int(size[i, 0]), int(size[i, 1]), (K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]))
        frames.append(Frame(name=name, image_path=image, camera=cam, split="train", R=R[i], t=t[i]))
        obs[name] = (kp[off[i]:off[i + 1]].astype(np.int64), uv[off[i]:off[i + 1]])
    return frames, obs
