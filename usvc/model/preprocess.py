"""Image -> network input exactly as ACE prepares it, so published encoder weights apply."""

from __future__ import annotations

import cv2
import numpy as np
import torch

LUMA_WEIGHTS_RGB = (0.299, 0.587, 0.114)
INPUT_MEAN = 0.4
INPUT_STD = 0.25


def resize_to_short_side(image: np.ndarray, short_side: int = 480) -> tuple[np.ndarray, float]:
    """Bilinear resize so min(H, W) == short_side; returns (image, scale).

    The short side is exact and the long side is rounded to the nearest pixel, so `scale`
    (short_side / old short side) is the factor to apply to focal lengths and principal points.
    """
    if image.ndim not in (2, 3):
        raise ValueError(f"expected an HxW or HxWxC image, got shape {image.shape}")
    h, w = image.shape[:2]
    scale = short_side / min(h, w)
    if h <= w:
        new_h, new_w = short_side, int(round(w * scale))
    else:
        new_h, new_w = int(round(h * scale)), short_side
    if (new_h, new_w) == (h, w):
        return image, 1.0
    return cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR), scale


def luma01(image: np.ndarray, rgb: bool) -> np.ndarray:
    """uint8 HxWx3 (RGB if `rgb`, else BGR) or HxW grey -> HxW float32 luma in [0, 1]."""
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        luma = image.astype(np.float32)
    elif image.ndim == 3 and image.shape[2] == 3:
        weights = LUMA_WEIGHTS_RGB if rgb else LUMA_WEIGHTS_RGB[::-1]
        pixels = image.astype(np.float32)
        luma = sum(pixels[..., c] * weights[c] for c in range(3))
    else:
        raise ValueError(f"expected HxW or HxWx3, got shape {image.shape}")
    return (luma / 255.0).astype(np.float32)


def normalise(gray01: np.ndarray) -> torch.Tensor:
    """HxW luma in [0, 1] (possibly augmented) -> (1, 1, H, W) network input."""
    normalised = (gray01 - INPUT_MEAN) / INPUT_STD
    return torch.from_numpy(np.ascontiguousarray(normalised, dtype=np.float32))[None, None]
