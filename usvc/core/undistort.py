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

Implausible distortion is caught before any image is resampled (``check_distortion``): a model
whose distorted radius stops growing inside the image (it folds over: k1 = -5 turns back a short
way from the centre) cannot be undistorted and is refused; one whose undistorted view keeps
little of the photo (k1 = +5 shrinks a 640x360 photo to about 230x130) is warned about.
"""

from __future__ import annotations

import logging
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from usvc.core.errors import SceneError
from usvc.core.scene import Camera

log = logging.getLogger(__name__)

FOV_MODES = {"crop": 0.0, "full": 1.0}
# An undistorted view (same focal length) narrower or lower than this fraction of the photo, or
# seeing less than this fraction of its area, is warned about: real lenses keep far more (60-100 %
# per side and 55-100 % of the area for fisheyes and phone lenses; k1 = +5 keeps 36-55 % per side).
MIN_KEPT_SIDE = 0.6
MIN_KEPT_AREA = 0.5
# A model that folds over before this fraction of the way from the principal point to the image
# border is refused; one that folds only in the outermost corner (an over-fitted k3) is warned about.
MAX_FOLD_FRACTION = 0.9
_FOLD_ANGLES_DEG = np.linspace(0.0, 89.5, 4000)  # ray angles from the optical axis, sampled for the fold test
_FOLD_DIRECTIONS = 64  # azimuths sampled around the principal point


def to_pycolmap(camera: Camera) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                           params=list(camera.params))


def describe(camera: Camera) -> str:
    return f"{camera.model} {camera.width}x{camera.height} (params {', '.join(f'{v:g}' for v in camera.params)})"


def fold_radius_px(camera: Camera) -> tuple[float, float] | None:
    """(where, how far the image reaches) in pixels from the principal point along the first
    direction in which the distorted model folds over, i.e. the image point of a ray stops moving
    outwards while still inside the image; None when the model is monotonic over the whole image.

    Rays are sampled by their angle from the optical axis up to 89.5 degrees, so a fisheye whose
    image reaches past 90 degrees is not a fold (its pinhole view is cropped instead)."""
    tan = np.tan(np.radians(_FOLD_ANGLES_DEG))
    az = np.linspace(0.0, 2 * np.pi, _FOLD_DIRECTIONS, endpoint=False)
    rays = np.stack([np.outer(np.cos(az), tan).ravel(), np.outer(np.sin(az), tan).ravel(),
                     np.ones(az.size * tan.size)], axis=1)
    with np.errstate(all="ignore"):
        xy = to_pycolmap(camera).img_from_cam(rays, check_cheirality=False).reshape(az.size, tan.size, 2)
    c = np.array(camera.principal_point)
    dist = np.linalg.norm(xy - c, axis=2)
    inside = ((xy[..., 0] >= 0) & (xy[..., 1] >= 0) & (xy[..., 0] <= camera.width) & (xy[..., 1] <= camera.height)
              & np.isfinite(dist))
    worst: tuple[float, float] | None = None
    for k in range(az.size):
        # the first sample that left the image (or became invalid) ends this direction's check
        n = int(np.argmin(inside[k])) if not inside[k].all() else tan.size
        d = dist[k, :n]
        turns = np.flatnonzero(np.diff(d) <= 0)
        if turns.size:
            fold = float(d[turns[0]]), _reach_px(camera, az[k])
            if worst is None or fold[0] / fold[1] < worst[0] / worst[1]:
                worst = fold
    return worst


def _reach_px(camera: Camera, azimuth: float) -> float:
    """Distance from the principal point to the image border along ``azimuth`` (at least 1 px)."""
    (cx, cy), (dx, dy) = camera.principal_point, (np.cos(azimuth), np.sin(azimuth))
    steps = [((camera.width if dx > 0 else 0.0) - cx) / dx if abs(dx) > 1e-12 else np.inf,
             ((camera.height if dy > 0 else 0.0) - cy) / dy if abs(dy) > 1e-12 else np.inf]
    return max(1.0, float(min(s for s in steps if s >= 0)))


def kept_fraction(camera: Camera, pinhole: Camera) -> float:
    """Fraction of ``camera``'s image area that the undistorted ``pinhole`` view sees (on a grid)."""
    n = 48
    u, v = np.meshgrid((np.arange(n) + 0.5) * camera.width / n, (np.arange(n) + 0.5) * camera.height / n)
    rays = to_pycolmap(camera).cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    (fx, fy), (cx, cy) = pinhole.focal, pinhole.principal_point
    with np.errstate(all="ignore"):
        x, y = rays[:, 0] * fx + cx, rays[:, 1] * fy + cy
        seen = (x >= 0) & (y >= 0) & (x <= pinhole.width) & (y <= pinhole.height)
    return float(np.mean(seen))


@lru_cache(maxsize=64)
def _distortion_problems(camera: Camera, fov: str) -> tuple[str, str]:
    """(why it cannot be undistorted, why it is doubtful); empty strings when fine."""
    fold = fold_radius_px(camera)
    if fold is not None:
        what = (f"its lens distortion folds over: the distorted radius stops growing {fold[0]:.0f} px from the "
                f"principal point, inside the image (which reaches {fold[1]:.0f} px there), so ")
        if fold[0] < MAX_FOLD_FRACTION * fold[1]:
            return what + ("the photo cannot be undistorted: are the distortion parameters wrong, or in another "
                           "convention than COLMAP's (normalized image coordinates)?"), ""
        return "", what + "the outermost corner cannot be undistorted (over-fitted distortion parameters?)"
    pinhole = _undistorted_camera(camera, fov)
    side = min(pinhole.width / camera.width, pinhole.height / camera.height)
    area = kept_fraction(camera, pinhole)
    if side < MIN_KEPT_SIDE or area < MIN_KEPT_AREA:
        return "", (f"undistorting it (fov={fov}) keeps a {pinhole.width}x{pinhole.height} pinhole image, "
                    f"{100 * side:.0f}% of the photo's side and {100 * area:.0f}% of its area: extreme distortion, "
                    "or wrong distortion parameters?")
    return "", ""


_warned: set[tuple[Camera, str]] = set()


def check_distortion(camera: Camera, fov: str = "crop", where: str = "") -> None:
    """Refuse a distortion model that folds over inside the image; warn (once per camera) when the
    undistorted view keeps little of the photo. ``where`` names the photos of this camera."""
    if fov not in FOV_MODES:
        raise SceneError(f"undistortion field of view {fov!r} is not one of {sorted(FOV_MODES)}")
    if not camera.has_distortion:
        return
    refusal, doubt = _distortion_problems(camera, fov)
    of = f" of {where}" if where else ""
    if refusal:
        raise SceneError(f"camera {describe(camera)}{of}: {refusal}")
    if doubt and (camera, fov) not in _warned:
        _warned.add((camera, fov))
        log.warning("camera %s%s: %s", describe(camera), of, doubt)


def undistorted_camera(camera: Camera, fov: str = "crop") -> Camera:
    """The PINHOLE camera the image of ``camera`` is resampled to (itself when undistorted).
    Distortion that cannot be undistorted is refused (:func:`check_distortion`)."""
    if fov not in FOV_MODES:
        raise SceneError(f"undistortion field of view {fov!r} is not one of {sorted(FOV_MODES)}")
    if camera.has_distortion:
        check_distortion(camera, fov)
    return _undistorted_camera(camera, fov)


def _undistorted_camera(camera: Camera, fov: str) -> Camera:
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

