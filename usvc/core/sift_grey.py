"""The grey image every SIFT in usvc runs on: the one COLMAP's image reader makes of a colour photo.

The sfm stage's SIFT (COLMAP's `extract_features`) reads each mapping photo through COLMAP's own
reader, which converts colour to grey by the Rec. 709 luma (0.2126 R + 0.7152 G + 0.0722 B),
rounded to the nearest level. A query's SIFT must see the same grey for its keypoints and
descriptors to be the landmarks' kind: the network's Rec. 601 luma (`usvc.model.preprocess.luma01`)
differs by up to a few levels on a fifth of a colour photo's pixels, which moves keypoints by
hundredths of a pixel and their descriptors with them (docs/results.md, "The query's SIFT sees
COLMAP's grey").
"""

from __future__ import annotations

import numpy as np

COLMAP_GREY_WEIGHTS_RGB = (0.2126, 0.7152, 0.0722)  # COLMAP's Bitmap::CloneAsGrey (Rec. 709 luma)


def colmap_grey(image: np.ndarray, rgb: bool) -> np.ndarray:
    """uint8 HxWx3 (RGB if `rgb`, else BGR) or HxW grey -> HxW uint8 grey, as COLMAP's reader
    converts it: the weighted sum in float32, in R, G, B order, rounded half up (the same levels as
    `pycolmap.Bitmap.clone_as_grey`, ties included)."""
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected HxW or HxWx3, got shape {image.shape}")
    r, g, b = (image[..., 0], image[..., 1], image[..., 2]) if rgb else (image[..., 2], image[..., 1], image[..., 0])
    wr, wg, wb = (np.float32(w) for w in COLMAP_GREY_WEIGHTS_RGB)
    luma = (r.astype(np.float32) * wr + g.astype(np.float32) * wg) + b.astype(np.float32) * wb
    return np.clip(np.floor(luma.astype(np.float64) + 0.5), 0, 255).astype(np.uint8)
