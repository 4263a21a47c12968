"""Render a procedural room and write it in the ACE/DSAC* dataset layout, atomically.

Layout written under ``out_dir`` (frames of seq-01.. in train/, the query sequence in test/):
``<split>/rgb/<seq>-frame-NNNNNN.color.png`` (RGB), ``<split>/depth/...depth.png`` (uint16 mm,
0 = invalid), ``<split>/poses/...pose.txt`` (4x4 camera-to-world, OpenCV axes, metres) and
``<split>/calibration/...calibration.txt`` (focal in px, fx = fy, principal point W/2, H/2),
plus ``scene.json`` with the parameters and conventions.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from usvc.core.atomic import atomic_dir
from usvc.core.errors import UsvcError
from usvc.generate.params import RoomParams, validate
from usvc.generate.room import Layout, cast, make_layout, pixel_rects
from usvc.generate.textures import Atlas, build_atlas
from usvc.generate.trajectory import Sequence, make_sequences

log = logging.getLogger(__name__)

CONVENTIONS = {
    "world": "metres, z up, floor at z = 0, room interior [0, room_x] x [0, room_y] x [0, room_z]",
    "poses": "4x4 camera-to-world, OpenCV camera axes (x right, y down, z forward)",
    "intrinsics": "pinhole, fx = fy = focal, principal point (W/2, H/2), pixel centres at +0.5 (COLMAP)",
    "depth": "uint16 PNG in millimetres along the optical axis (z), 0 = invalid",
}


def intrinsics(params: RoomParams) -> np.ndarray:
    """The 3x3 pinhole matrix of every frame (COLMAP pixel convention)."""
    f = params.focal
    return np.array([[f, 0.0, params.width / 2], [0.0, f, params.height / 2], [0.0, 0.0, 1.0]])


def pixel_rays(width: int, height: int, focal: float) -> np.ndarray:
    """(3, H, W) float32 camera rays K^-1 [j + 0.5, i + 0.5, 1]; z = 1 so the ray length t is depth."""
    x = (np.arange(width) + 0.5 - width / 2) / focal
    y = (np.arange(height) + 0.5 - height / 2) / focal
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy, np.ones_like(xx)]).astype(np.float32)


class Renderer:
    """Renders RGB and exact depth of one scene from any camera-to-world pose."""

    def __init__(self, params: RoomParams, layout: Layout | None = None, atlas: Atlas | None = None) -> None:
        validate(params)
        self.params = params
        self.layout = layout if layout is not None else make_layout(params)
        self.atlas = atlas if atlas is not None else build_atlas(self.layout, params)
        s = params.supersample
        self._rays_fine = pixel_rays(params.width * s, params.height * s, params.focal * s)
        self._rays = self._rays_fine if s == 1 else pixel_rays(params.width, params.height, params.focal)

    def _cast(self, cam_to_world: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ray directions (3, h, w), hit distance t (= depth) and face of a ray grid."""
        _, h, w = rays.shape
        dirs = (cam_to_world[:3, :3].astype(np.float32) @ rays.reshape(3, -1)).reshape(3, h, w)
        focal = self.params.focal * w / self.params.width
        rects = pixel_rects(self.layout, cam_to_world, focal, w, h)
        t, face = cast(cam_to_world[:3, 3], dirs, self.layout, rects)
        return dirs, t, face

    def depth(self, cam_to_world: np.ndarray) -> np.ndarray:
        """(H, W) float32 z-depth in metres at the pixel centres; the closed room hits everywhere."""
        return self._cast(cam_to_world, self._rays)[1]

    def render(self, cam_to_world: np.ndarray, noise_seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(RGB uint8 (H, W, 3), depth float32 (H, W)); sensor noise is seeded by ``noise_seed``."""
        p = self.params
        dirs, t, face = self._cast(cam_to_world, self._rays_fine)
        points = cam_to_world[:3, 3].astype(np.float32)[:, None, None] + t * dirs
        col, row = self.atlas.lookup(points, face)
        image = cv2.remap(self.atlas.image, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if p.supersample > 1:
            image = cv2.resize(image, (p.width, p.height), interpolation=cv2.INTER_AREA)
            t = self.depth(cam_to_world)
        if p.image_noise > 0:
            rng = np.random.default_rng([p.seed, 505, noise_seed])
            image += p.image_noise * rng.standard_normal(image.shape, dtype=np.float32)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8), t


def depth_to_png(depth: np.ndarray) -> np.ndarray:
    """Metres to uint16 millimetres; non-finite, non-positive or out-of-range depth becomes 0."""
    mm = np.rint(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * 1000.0)
    return np.where((mm > 0) & (mm <= 65535), mm, 0).astype(np.uint16)


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise UsvcError(f"could not write {path}")


def _write_frames(root: Path, renderer: Renderer, sequences: list[Sequence]) -> dict[str, int]:
    """Render every frame of every sequence into ``root``; returns frames per split."""
    counts: dict[str, int] = {}
    for split in sorted({seq.split for seq in sequences}):
        for sub in ("rgb", "depth", "poses", "calibration"):
            (root / split / sub).mkdir(parents=True, exist_ok=True)
    total = sum(len(seq.cam_to_world) for seq in sequences)
    focal = f"{renderer.params.focal:.9f}\n"
    frame_id = 0
    with tqdm(total=total, desc="render", unit="frame", disable=None) as bar:
        for seq in sequences:
            log.info("rendering %s (%s, %d frames)", seq.name, seq.split, len(seq.cam_to_world))
            for i, pose in enumerate(seq.cam_to_world):
                stem = f"{seq.name}-frame-{i:06d}"
                rgb, depth = renderer.render(pose, frame_id)
                split = root / seq.split
                _imwrite(split / "rgb" / f"{stem}.color.png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                _imwrite(split / "depth" / f"{stem}.depth.png", depth_to_png(depth))
                np.savetxt(split / "poses" / f"{stem}.pose.txt", pose, fmt="%.9f")
                (split / "calibration" / f"{stem}.calibration.txt").write_text(focal)
                counts[seq.split] = counts.get(seq.split, 0) + 1
                frame_id += 1
                bar.update(1)
    return counts


def _scene_record(params: RoomParams, layout: Layout, sequences: list[Sequence],
                  counts: dict[str, int]) -> dict:
    return {
        "generator": "usvc.synth",
        "params": asdict(params),
        "conventions": CONVENTIONS,
        "counts": counts,
        "sequences": {s.name: {"split": s.split, "frames": len(s.cam_to_world)} for s in sequences},
        "boxes": [{"lo": lo.tolist(), "hi": hi.tolist()} for lo, hi in zip(layout.lo, layout.hi)],
        "lights": layout.lights.tolist(),
    }


def generate_scene(out_dir: Path, params: RoomParams) -> dict:
    """Render the scene of ``params`` into ``out_dir`` (replaced whole, never left half-written).

    Frames go to a temporary sibling directory that is renamed onto ``out_dir`` at the end and
    removed on any failure. Returns frames per split and the seconds taken.
    """
    validate(params)
    out_dir = Path(out_dir)
    start = time.perf_counter()
    with atomic_dir(out_dir) as tmp:
        layout = make_layout(params)
        sequences = make_sequences(params, layout)
        atlas = build_atlas(layout, params)
        log.info("scene seed %d: %d boxes, atlas %dx%d, %.1f s setup", params.seed, layout.n_boxes - 1,
                 atlas.image.shape[1], atlas.image.shape[0], time.perf_counter() - start)
        counts = _write_frames(tmp, Renderer(params, layout, atlas), sequences)
        record = _scene_record(params, layout, sequences, counts)
        (tmp / "scene.json").write_text(json.dumps(record, indent=2) + "\n")
    seconds = time.perf_counter() - start
    log.info("wrote %s: %s frames in %.1f s", out_dir, counts, seconds)
    return {"train_frames": counts.get("train", 0), "test_frames": counts.get("test", 0), "seconds": seconds}
