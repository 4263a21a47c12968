"""ACE / DSAC* layout: ``<root>/{train,test}/{rgb,poses,calibration}/`` (+ optional ``depth/``).

Files pair up by sorted file name within each folder, so the folders must hold equally many.
Poses are 4x4 camera-to-world in OpenCV axes. A calibration file holds either one focal
length (principal point at the image centre, COLMAP's (W/2, H/2), which is where ACE puts
it) or a 3x3 K kept as given. Depth maps are 16-bit millimetres. Scene units are metres in
this layout, so the metric scale defaults to 1.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.scene import Camera, Frame, Scene, every_nth_split
from usvc.prepare.importers.common import (
    as_matrix,
    image_size,
    list_images,
    make_camera,
    make_frame,
    read_matrix_txt,
    world_to_cam_from_cam_to_world,
)

log = logging.getLogger(__name__)

SPLIT_DIRS = ("train", "test")
DEPTH_SCALE = 0.001  # millimetres to metres


def _files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise SceneError(f"missing folder {folder}")
    return sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")), key=lambda p: p.name)


def _check_count(folder: Path, files: list[Path], rgb_dir: Path, n_rgb: int) -> None:
    if len(files) != n_rgb:
        raise SceneError(f"{folder}: {len(files)} files but {rgb_dir} has {n_rgb} images")


def _camera(calib_file: Path, size: tuple[int, int]) -> Camera:
    """PINHOLE camera from a one-number focal or a 3x3 K calibration file."""
    m = read_matrix_txt(calib_file)
    W, H = size
    where = str(calib_file)
    if m.size == 1:
        f = float(m.flat[0])
        if not (np.isfinite(f) and f > 0):
            raise SceneError(f"{calib_file}: focal length must be positive, got {f}")
        return make_camera(where, "PINHOLE", W, H, (f, f, W / 2.0, H / 2.0))
    K = as_matrix(m, [(3, 3)], where, "calibration")
    return make_camera(where, "PINHOLE", W, H, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))


def _split_frames(root: Path, split: str) -> list[Frame]:
    d = root / split
    rgb_dir = d / "rgb"
    rgb = list_images(rgb_dir)
    poses = _files(d / "poses")
    calib = _files(d / "calibration")
    _check_count(d / "poses", poses, rgb_dir, len(rgb))
    _check_count(d / "calibration", calib, rgb_dir, len(rgb))
    depth: list[Path | None] = [None] * len(rgb)
    if (d / "depth").is_dir():
        depth_files = _files(d / "depth")
        _check_count(d / "depth", depth_files, rgb_dir, len(rgb))
        depth = list(depth_files)
    if not rgb:
        return []
    # ACE datasets store one resolution per split; reading every header would dominate load time.
    size = image_size(rgb[0])
    frames = []
    for img, pose_file, calib_file, depth_file in zip(rgb, poses, calib, depth):
        T = as_matrix(read_matrix_txt(pose_file), [(4, 4), (3, 4)], str(pose_file))
        R, t = world_to_cam_from_cam_to_world(T[:3, :3], T[:3, 3], str(pose_file))
        frames.append(
            make_frame(
                str(pose_file),
                name=img.relative_to(root).as_posix(),
                image_path=img,
                camera=_camera(calib_file, size),
                split=split,
                R=R,
                t=t,
                depth_path=depth_file,
                depth_scale=DEPTH_SCALE,
            )
        )
    return frames


def load(root: Path, name: str, split_rule: str, split_n: int, metric_scale: float | None) -> Scene:
    """Import an ACE-layout scene; ``given`` uses the train/test folders.

    ``every_nth`` re-splits train-then-test in sorted order and tolerates a missing split
    folder, so a capture written only as ``train/`` can still be evaluated.
    """
    present = [s for s in SPLIT_DIRS if (root / s).is_dir()]
    if split_rule == "given" or not present:
        present = list(SPLIT_DIRS)
    frames = [f for split in present for f in _split_frames(root, split)]
    if split_rule == "every_nth":
        for frame, split in zip(frames, every_nth_split(split_n, len(frames))):
            frame.split = split
    log.info("ace %s: %d frames", name, len(frames))
    return Scene(name=name, frames=frames, metric_scale=1.0 if metric_scale is None else metric_scale, root=root)
