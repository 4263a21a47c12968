"""Lens undistortion: any supported COLMAP camera -> a PINHOLE camera and a resampled image.

COLMAP's own camera models define what the parameters mean, so COLMAP (pycolmap) chooses the
undistorted camera (``undistort_camera``: same focal length, principal point at the centre, the
size chosen by ``blank_pixels``) and projects every pixel of it through the distorted model
(``Camera.img_from_cam``). OpenCV's ``remap`` then resamples the image with those coordinates,
so one precomputed map serves every image of a camera (mapping images, depth maps, queries).

Field of view (``fov``):
- ``crop`` (default, COLMAP ``blank_pixels=0``): the largest pinhole view with no black border;
  the strongly distorted corners are cut off.
- ``full`` (``blank_pixels=1``): every source pixel is kept; the corners then hold black
  (invalid) pixels, which the encoder would see as texture.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from usvc.core.errors import SceneError
from usvc.core.scene import Camera

FOV_MODES = {"crop": 0.0, "full": 1.0}


def to_pycolmap(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                           params=list(camera.params))


def undistorted_camera(camera: Camera, fov: str = "crop") -> Camera:
    """The PINHOLE camera the image of ``camera`` is resampled to (itself when undistorted)."""
    if fov not in FOV_MODES:
        raise SceneError(f"undistortion field of view {fov!r} is not one of {sorted(FOV_MODES)}")
    if not camera.has_distortion:
        (fx, fy), (cx, cy) = camera.focal, camera.principal_point
        return Camera("PINHOLE", camera.width, camera.height, (fx, fy, cx, cy))
    options = pycolmap.UndistortCameraOptions()
    options.blank_pixels = FOV_MODES[fov]
    out = pycolmap.undistort_camera(options, to_pycolmap(camera))
    if out.model.name != "PINHOLE":  # pragma: no cover - COLMAP always returns PINHOLE
        raise SceneError(f"COLMAP undistorted {camera.model} to {out.model.name}, expected PINHOLE")
    return Camera("PINHOLE", int(out.width), int(out.height), tuple(float(v) for v in out.params))


@lru_cache(maxsize=8)
def _maps(src: Camera, dst: Camera) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of ``dst``, where to sample ``src`` (OpenCV pixel-centre convention)."""
    u, v = np.meshgrid(np.arange(dst.width) + 0.5, np.arange(dst.height) + 0.5)
    (fx, fy), (cx, cy) = dst.focal, dst.principal_point
    rays = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=1)
    xy = to_pycolmap(src).img_from_cam(rays, check_cheirality=False) - 0.5  # COLMAP -> OpenCV centres
    xy = xy.reshape(dst.height, dst.width, 2).astype(np.float32)
    return np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])


def check_image_size(image: np.ndarray, camera: Camera, where: str) -> None:
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        hint = ""
        if (h, w) == (camera.width, camera.height) and Path(where).is_file():
            from usvc.core.exif import exif_orientation

            turn = exif_orientation(where)
            if turn in (5, 6, 7, 8):
                hint = (f" (its EXIF orientation {turn} turns it by 90 degrees, as viewers show it; the camera "
                        f"must describe the turned {w}x{h} image)")
        raise SceneError(f"{where}: image is {w}x{h} but its camera says {camera.width}x{camera.height}{hint}")


def resample(image: np.ndarray, src: Camera, dst: Camera, nearest: bool = False) -> np.ndarray:
    """``image`` taken by ``src`` as seen by ``dst`` (same centre and orientation).

    Bilinear for photos, nearest for depth maps (interpolating across an occlusion boundary
    invents depths); pixels ``src`` never saw are 0.
    """
    map_x, map_y = _maps(src, dst)
    return cv2.remap(image, map_x, map_y, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def undistort(image: np.ndarray, camera: Camera, fov: str = "crop", where: str = "image",
              nearest: bool = False) -> tuple[np.ndarray, Camera]:
    """(undistorted image, its PINHOLE camera); a pinhole camera passes through untouched."""
    check_image_size(image, camera, where)
    pinhole = undistorted_camera(camera, fov)
    if not camera.has_distortion:
        return image, pinhole
    return resample(image, camera, pinhole, nearest=nearest), pinhole


def valid_mask(src: Camera, dst: Camera) -> np.ndarray:
    """Pixels of ``dst`` that fall inside ``src``'s image (where ``resample`` has data)."""
    map_x, map_y = _maps(src, dst)
    return (map_x >= -0.5) & (map_y >= -0.5) & (map_x <= src.width - 0.5) & (map_y <= src.height - 0.5)


def distort_pinhole(image: np.ndarray, pinhole: Camera, distorted: Camera) -> np.ndarray:
    """Render what a lens with ``distorted``'s model would have recorded of a pinhole image.

    Used to make distorted test scenes from pinhole captures; pixels outside ``pinhole``'s view
    are 0. ``distorted`` is the same size as ``pinhole`` unless given otherwise.
    """
    check_image_size(image, pinhole, "pinhole image")
    h, w = distorted.height, distorted.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = to_pycolmap(distorted).cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    (fx, fy), (cx, cy) = pinhole.focal, pinhole.principal_point
    xy = np.stack([rays[:, 0] * fx + cx, rays[:, 1] * fy + cy], axis=1) - 0.5
    xy = xy.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1]),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

