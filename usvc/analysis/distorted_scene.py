"""Make a lens-distorted copy of a pinhole scene, to prove that undistortion recovers it.

Every image is re-rendered through a distorted camera model (``usvc.core.undistort.distort_pinhole``)
with the same pose, and the scene is written in a format that carries that model: nerfstudio's
``transforms.json`` (OPENCV, OPENCV_FISHEYE) or a COLMAP text model (any supported model). The
distorted camera's focal length is raised just enough that every distorted pixel sees inside the
original image, so the copy has no black corners, as a real photo has none.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from usvc.core.errors import SceneError
from usvc.core.scene import CAMERA_MODELS, Camera, Scene
from usvc.core.undistort import (
    distort_pinhole,
    resample,
    to_pycolmap,
    undistort,
    valid_mask,
)

log = logging.getLogger(__name__)

# Distortion coefficients (after fx fy cx cy, or f cx cy) per model: OPENCV's are those of a real
# phone capture exported by nerfstudio; the others are typical of phone and action cameras.
DEFAULT_DISTORTION: dict[str, tuple[float, ...]] = {
    "OPENCV": (0.058, -0.081, 0.0004, -0.0003),
    "SIMPLE_RADIAL": (-0.06,),
    "RADIAL": (-0.06, 0.02),
    "OPENCV_FISHEYE": (0.05, -0.02, 0.0, 0.0),
}
FORMATS = {"transforms": ("OPENCV", "OPENCV_FISHEYE"), "colmap": tuple(DEFAULT_DISTORTION)}
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class DistortOptions:
    model: str = "OPENCV"
    fmt: str = "transforms"
    coefficients: tuple[float, ...] | None = None  # None: DEFAULT_DISTORTION[model]
    jpeg_quality: int = 95


def distorted_camera(pinhole: Camera, model: str, coefficients: tuple[float, ...]) -> Camera:
    """``model`` with ``coefficients``, focal scaled so its whole image lies inside ``pinhole``'s."""
    (fx, fy), (cx, cy) = pinhole.focal, pinhole.principal_point
    n = CAMERA_MODELS[model] - len(coefficients)
    if n not in (3, 4):
        raise SceneError(f"{model} takes {CAMERA_MODELS[model]} parameters; {len(coefficients)} coefficients "
                         "leave no room for its focal length and principal point")

    def make(scale: float) -> Camera:
        head = (fx * scale, cx, cy) if n == 3 else (fx * scale, fy * scale, cx, cy)
        return Camera(model, pinhole.width, pinhole.height, (*head, *coefficients))

    w, h = pinhole.width, pinhole.height
    edge = np.concatenate([np.stack([np.linspace(0, w, 64), np.full(64, y)], 1) for y in (0, h)]
                          + [np.stack([np.full(64, x), np.linspace(0, h, 64)], 1) for x in (0, w)])
    scale = 1.0
    for _ in range(20):  # fixed point: the scale that puts the farthest border ray on the border
        rays = to_pycolmap(make(scale)).cam_from_img(edge)
        need = max(np.max(np.abs(rays[:, 0]) * fx / max(cx, w - cx)), np.max(np.abs(rays[:, 1]) * fy / max(cy, h - cy)))
        if need <= 1.0:
            break
        scale *= need * 1.001
    return make(scale)


def _write_transforms(out: Path, scene: Scene, cameras: list[Camera], names: list[str]) -> None:
    frames = []
    for f, cam, name in zip(scene.frames, cameras, names):
        cam_to_world = np.eye(4)
        cam_to_world[:3, :3] = f.R.T @ _GL_FROM_CV
        cam_to_world[:3, 3] = f.center
        p = cam.params
        entry = {"file_path": f"images/{name}", "transform_matrix": cam_to_world.tolist(), "camera_model": cam.model,
                 "fl_x": p[0], "fl_y": p[1], "cx": p[2], "cy": p[3], "w": cam.width, "h": cam.height}
        keys = ("k1", "k2", "p1", "p2") if cam.model == "OPENCV" else ("k1", "k2", "k3", "k4")
        entry.update(dict(zip(keys, p[4:8])))
        frames.append(entry)
    (out / "transforms.json").write_text(json.dumps({"frames": frames}, indent=1) + "\n")


def _write_colmap(out: Path, scene: Scene, cameras: list[Camera], names: list[str]) -> None:
    rec = pycolmap.Reconstruction()
    ids: dict[Camera, int] = {}
    for image_id, (f, cam, name) in enumerate(zip(scene.frames, cameras, names), start=1):
        if cam not in ids:
            ids[cam] = len(ids) + 1
            pc = to_pycolmap(cam)
            pc.camera_id = ids[cam]
            rec.add_camera_with_trivial_rig(pc)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=ids[cam], image_id=image_id),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(f.R), f.t))
    model_dir = out / "sparse" / "0"
    model_dir.mkdir(parents=True)
    rec.write_text(str(model_dir))


def write_distorted_scene(scene: Scene, out: Path, options: DistortOptions) -> dict:
    """Write the distorted copy of ``scene`` (pinhole, posed) into the empty folder ``out``."""
    if options.fmt not in FORMATS or options.model not in FORMATS[options.fmt]:
        raise SceneError(f"format {options.fmt!r} cannot carry camera model {options.model!r}; "
                         f"supported: {FORMATS}")
    coefficients = options.coefficients if options.coefficients is not None else DEFAULT_DISTORTION[options.model]
    if not scene.has_poses:
        raise SceneError(f"scene {scene.name!r} has no poses to carry over")
    (out / "images").mkdir(parents=True)
    cameras, names = [], []
    # Names carry the source order, so every importer (some sort naturally, some lexicographically)
    # lists the frames in the source's order and an every_nth split picks the same queries.
    for i, f in enumerate(tqdm(scene.frames, desc=f"distort {scene.name} ({options.model})", unit="img")):
        if f.camera.has_distortion:
            raise SceneError(f"{f.image_path}: source camera {f.camera.model} already has distortion")
        image = cv2.imread(str(f.image_path), cv2.IMREAD_COLOR)
        if image is None:
            raise SceneError(f"cannot read image {f.image_path}")
        cam = distorted_camera(f.camera, options.model, coefficients)
        name = f"{i:04d}_{Path(f.name).stem}.jpg"
        if not cv2.imwrite(str(out / "images" / name), distort_pinhole(image, f.camera, cam),
                           [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality]):
            raise SceneError(f"cannot write {out / 'images' / name}")
        cameras.append(cam)
        names.append(name)
    (_write_transforms if options.fmt == "transforms" else _write_colmap)(out, scene, cameras, names)
    first = cameras[0]
    return {"frames": len(names), "model": first.model, "params": list(first.params),
            "focal_scale": first.params[0] / scene.frames[0].camera.focal[0], "format": options.fmt,
            "names": dict(zip((f.name for f in scene.frames), names))}


def undistortion_psnr(original: np.ndarray, original_camera: Camera, distorted: np.ndarray,
                      distorted_camera_: Camera, fov: str = "crop") -> tuple[float, float]:
    """(PSNR in dB, valid fraction): the undistorted copy against the original seen by the same
    pinhole camera, over the pixels both have data for."""
    image, pinhole = undistort(distorted, distorted_camera_, fov)
    reference = resample(original, original_camera, pinhole)
    valid = valid_mask(original_camera, pinhole) & valid_mask(distorted_camera_, pinhole)
    err = (image.astype(np.float64) - reference.astype(np.float64))[valid]
    mse = float(np.mean(err**2))
    return (float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)), float(valid.mean())

