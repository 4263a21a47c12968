"""What a query brings: its photo (a path or an array) as float luma, its intrinsics in any of the
forms the API takes, and the torch device to run on, each checked with one clear line; and a photo
that is no camera view (too small, a strip) or blank."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from usvc.core.device import DEVICE_CHOICES, device_problem, resolve_device
from usvc.core.errors import UsvcError
from usvc.core.images import read_image_bgr
from usvc.core.scene import Camera
from usvc.model.preprocess import luma01

Intrinsics = float | Sequence[float] | np.ndarray | Camera
MIN_IMAGE_SIDE = 32
MAX_ASPECT = 4  # long side / short side of a query photo (phones: 1.3-2.2)
# A photo below this contrast (std of its grey levels in [0, 1]) is blank: nothing to localize.
MIN_CONTRAST = 1.0 / 255.0


def camera_from_intrinsics(intrinsics: Intrinsics, width: int, height: int) -> Camera:
    """A focal (principal point at the image centre), (fx, fy, cx, cy), a 3x3 K or a Camera of
    any supported COLMAP model (with distortion)."""
    if isinstance(intrinsics, Camera):
        cam = intrinsics
        if (cam.width, cam.height) != (width, height):
            raise UsvcError(f"the camera is {cam.width}x{cam.height} but the image is {width}x{height}")
        return cam
    if isinstance(intrinsics, (bool, np.bool_)) or (isinstance(intrinsics, np.ndarray) and intrinsics.dtype == bool):
        raise UsvcError(f"intrinsics must be a focal, (fx, fy, cx, cy), a 3x3 K or a usvc Camera, got "
                        f"{intrinsics!r:.40} (a bool; None estimates the focal length)")
    if isinstance(intrinsics, (dict, str, bytes)):
        raise UsvcError(f"intrinsics must be a focal, (fx, fy, cx, cy), a 3x3 K or a usvc Camera, "
                        f"got a {type(intrinsics).__name__}")
    if isinstance(intrinsics, (list, tuple)) and any(isinstance(v, (bool, np.bool_)) for v in intrinsics):
        raise UsvcError(f"intrinsics must be numbers, got {intrinsics!r:.80} (holds a bool)")
    try:
        arr = np.asarray(intrinsics, dtype=np.float64)
    except (TypeError, ValueError):
        raise UsvcError(f"intrinsics must be a focal, (fx, fy, cx, cy), a 3x3 K or a usvc Camera, "
                        f"got {type(intrinsics).__name__} {intrinsics!r:.80}") from None
    if arr.size == 1:
        fx = fy = float(arr.reshape(-1)[0])
        cx, cy = width / 2, height / 2
    elif arr.shape == (4,):
        fx, fy, cx, cy = (float(v) for v in arr)
    elif arr.shape == (3, 3):
        fx, fy, cx, cy = float(arr[0, 0]), float(arr[1, 1]), float(arr[0, 2]), float(arr[1, 2])
    else:
        raise UsvcError(f"intrinsics must be a focal, (fx, fy, cx, cy) or a 3x3 K, got shape {arr.shape}")
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise UsvcError(f"intrinsics must be finite with positive focal lengths, got fx={fx}, fy={fy}")
    if not (0 < cx < width and 0 < cy < height):
        raise UsvcError(f"principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image: "
                        "wrong image size for these intrinsics?")
    return Camera("PINHOLE", width, height, (fx, fy, cx, cy))


def as_gray(image: np.ndarray | str | Path, channels: str = "rgb") -> np.ndarray:
    """Path or uint8 RGB/BGR/grey array -> float luma in [0, 1]."""
    if channels not in ("rgb", "bgr"):
        raise UsvcError(f"channels={channels!r} must be 'rgb' (PIL, imageio) or 'bgr' (cv2.imread)")
    if isinstance(image, (str, Path)):  # EXIF orientation applied, as for mapping images
        return luma01(read_image_bgr(image), rgb=False)
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise UsvcError(f"image must be a uint8 HxW or HxWx3 RGB array, got {arr.dtype} {arr.shape}")
    return luma01(arr, rgb=channels == "rgb")


def check_device(device: str) -> str:
    """The torch device to run on (`auto`: CUDA where torch sees one), checked (usvc.core.device)."""
    if not isinstance(device, str) or device_problem(device):
        raise UsvcError(f"device={device!r} is not a torch device usvc runs on ({DEVICE_CHOICES})")
    return resolve_device(device)


def check_size(width: int, height: int) -> None:
    """One UsvcError for a photo too small, or too long and thin, to be a camera view usvc localizes."""
    if min(height, width) < MIN_IMAGE_SIDE:
        raise UsvcError(f"image is {width}x{height}; need at least {MIN_IMAGE_SIDE} px on each side")
    if max(height, width) > MAX_ASPECT * min(height, width):
        aspect = max(height, width) / min(height, width)
        raise UsvcError(f"image is {width}x{height}, an aspect ratio of {aspect:.1f}:1; usvc localizes photos up to "
                        f"{MAX_ASPECT}:1 (a strip or panorama is not a camera view it can map)")


def blank(gray01: np.ndarray) -> str:
    """Why the photo is blank ("" when it is not): its grey levels vary by less than MIN_CONTRAST."""
    if float(gray01.std()) < MIN_CONTRAST:
        return (f"the photo is blank (its grey levels vary by {255 * float(gray01.std()):.2g} of 255): "
                "nothing to localize")
    return ""
