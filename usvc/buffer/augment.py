"""ACE-style augmentation of one mapping image: rescale, roll about the optical axis, photometric.

Pixel coordinates follow COLMAP (top-left pixel centre at (0.5, 0.5)); OpenCV's warps use integer
pixel centres, so affine maps are conjugated by a half-pixel shift before they reach OpenCV.

Geometry. The image is first resized so its short side becomes round(short_side * scale); with
sx = W'/W and sy = H'/H, COLMAP pixel coordinates map as (u, v) -> (sx u, sy v), so
K' = diag(sx, sy, 1) K (area averaging when shrinking, against aliasing, bilinear when enlarging;
both keep OpenCV's pixel-centre alignment, which is this map). It is then rolled by ``angle_deg``
about the principal point: the camera turns about its optical axis by Rz, so R' = Rz R,
t' = Rz t, and the image content moves by A = K' Rz K'^-1, an affine map that keeps the principal
point fixed and leaves K' unchanged. With square pixels A is the plain rotation that
cv2.getRotationMatrix2D((cx, cy), angle_deg, 1) gives (positive angle = content turns
counter-clockwise as displayed, y down); with fx != fy it is that rotation seen through the
anisotropic focal lengths, which keeps projections exact where a plain image rotation would not.
``roll_rotation`` gives Rz = [[cos a, sin a, 0], [-sin a, cos a, 0], [0, 0, 1]].

Photometric, on the source image before the warps: I' = clip(((I - mean(I)) * contrast + mean(I))
* brightness, 0, 1); contrast stretches about the mean so it does not shift overall exposure,
brightness then scales exposure.

Pixels of the rolled image that come from outside the source image are 0 and marked invalid in
``mask`` (a ones image warped with nearest-neighbour sampling).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class AugmentedView:
    """An augmented image with the camera that sees the scene exactly as it appears in it.

    ``scale`` is the drawn factor (short side = round(short_side * scale)). ``pixel_transform``
    (3x3) maps COLMAP pixel coordinates of the source image to those of the augmented image, so
    keypoints or targets found in the source image can follow the warp.
    """

    image: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    R_world_to_cam: np.ndarray
    t_world_to_cam: np.ndarray
    scale: float
    angle_deg: float
    brightness: float
    contrast: float
    pixel_transform: np.ndarray


def resized_shape(height: int, width: int, short_side: int) -> tuple[int, int]:
    """(H', W') with the short side equal to ``short_side`` and the aspect ratio kept (rounded)."""
    if height <= width:
        return short_side, max(1, round(width * short_side / height))
    return max(1, round(height * short_side / width)), short_side


def roll_rotation(angle_deg: float) -> np.ndarray:
    """Camera rotation about its optical axis that turns image content by ``angle_deg``.

    The sign matches cv2.getRotationMatrix2D: positive turns the content counter-clockwise on
    screen (y down).
    """
    a = np.deg2rad(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _to_opencv(A: np.ndarray) -> np.ndarray:
    """2x3 affine in OpenCV's integer-pixel-centre coordinates from a 3x3 one in COLMAP's."""
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    unshift = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    return (unshift @ A @ shift)[:2]


def _photometric(image: np.ndarray, brightness: float, contrast: float) -> np.ndarray:
    if brightness == 1.0 and contrast == 1.0:
        return image
    mean = float(image.mean())
    return np.clip(((image - mean) * contrast + mean) * brightness, 0.0, 1.0).astype(np.float32)


def warp_view(
    image: np.ndarray,
    K: np.ndarray,
    R_world_to_cam: np.ndarray,
    t_world_to_cam: np.ndarray,
    scale: float = 1.0,
    angle_deg: float = 0.0,
    brightness: float = 1.0,
    contrast: float = 1.0,
    short_side: int = 480,
) -> AugmentedView:
    """Apply one given augmentation (no randomness); ``augment`` draws its parameters."""
    if image.ndim != 2:
        raise ValueError(f"expected a grayscale (H, W) image, got shape {image.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"K must be 3x3 with last row [0, 0, 1], got {K.tolist()}")
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    src = _photometric(np.asarray(image, dtype=np.float32), brightness, contrast)

    h, w = src.shape
    h2, w2 = resized_shape(h, w, max(1, round(short_side * scale)))
    if (h2, w2) != (h, w):
        interp = cv2.INTER_AREA if h2 < h and w2 < w else cv2.INTER_LINEAR
        src = cv2.resize(src, (w2, h2), interpolation=interp)
    S = np.diag([w2 / w, h2 / h, 1.0])
    K2 = S @ K

    Rz = roll_rotation(angle_deg)
    A = K2 @ Rz @ np.linalg.inv(K2)
    A[2] = [0.0, 0.0, 1.0]
    if angle_deg == 0.0:
        out = np.array(src, dtype=np.float32)  # a copy: never alias the caller's image
        mask = np.ones((h2, w2), dtype=bool)
    else:
        M = _to_opencv(A)
        border = {"borderMode": cv2.BORDER_CONSTANT, "borderValue": 0}
        out = cv2.warpAffine(src, M, (w2, h2), flags=cv2.INTER_LINEAR, **border)
        ones = np.ones((h2, w2), dtype=np.uint8)
        mask = cv2.warpAffine(ones, M, (w2, h2), flags=cv2.INTER_NEAREST, **border).astype(bool)

    R = np.asarray(R_world_to_cam, dtype=np.float64)
    t = np.asarray(t_world_to_cam, dtype=np.float64).reshape(3)
    return AugmentedView(
        image=out.astype(np.float32, copy=False),
        mask=mask,
        K=K2,
        R_world_to_cam=Rz @ R,
        t_world_to_cam=Rz @ t,
        scale=float(scale),
        angle_deg=float(angle_deg),
        brightness=float(brightness),
        contrast=float(contrast),
        pixel_transform=A @ S,
    )


def augment(
    image_gray_float: np.ndarray,
    K: np.ndarray,
    R_world_to_cam: np.ndarray,
    t_world_to_cam: np.ndarray,
    rng: np.random.Generator,
    scale_range: tuple[float, float] = (1 / 1.5, 1.5),
    short_side: int = 480,
    max_rotation_deg: float = 15.0,
    brightness: tuple[float, float] = (0.9, 1.1),
    contrast: tuple[float, float] = (0.9, 1.1),
) -> AugmentedView:
    """Draw scale, angle, brightness and contrast (uniform, in that order) and apply them.

    The image is a grayscale float image in [0, 1]; deterministic given the state of ``rng``.
    """
    s = float(rng.uniform(*scale_range))
    angle = float(rng.uniform(-max_rotation_deg, max_rotation_deg))
    b = float(rng.uniform(*brightness))
    c = float(rng.uniform(*contrast))
    return warp_view(image_gray_float, K, R_world_to_cam, t_world_to_cam, s, angle, b, c, short_side)
