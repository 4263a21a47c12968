"""OpenCV's SIFT run as COLMAP's: the detector settings under which it finds most of COLMAP's
keypoints at COLMAP's positions, and its descriptors in COLMAP's form. Shared by the query's
features (usvc.relocalize.features.sift) and by the sfm stage when it extracts with OpenCV
(`sfm.extractor=opencv`), so both sides of a match come from one implementation.

COLMAP's peak threshold (0.02 / 3 octave layers) is OpenCV's contrast threshold / layers, and COLMAP
maps the doubled image's pixel x to 2x exactly, which OpenCV does only with precise upscaling (its
default upscaling shifts every keypoint by a quarter pixel). Keypoints come in COLMAP's pixel
convention (the top-left pixel's centre at (0.5, 0.5)); descriptors L1-root ("RootSIFT"), as COLMAP
normalises its own, either as unit float rows or in COLMAP's uint8 encoding (512 x value, rounded,
at most 255)."""

from __future__ import annotations

import functools

import cv2
import numpy as np

CONTRAST_THRESHOLD = 0.02


@functools.lru_cache(maxsize=4)
def opencv_sift(max_features: int) -> cv2.SIFT:
    return cv2.SIFT_create(nfeatures=max_features, contrastThreshold=CONTRAST_THRESHOLD, enable_precise_upscale=True)


def detect(gray_u8: np.ndarray, max_features: int) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """OpenCV's keypoints and unit L1-root float32 descriptors (K,128) of a uint8 grey image."""
    keypoints, descriptors = opencv_sift(int(max_features)).detectAndCompute(np.ascontiguousarray(gray_u8), None)
    if descriptors is None or not keypoints:
        return [], np.zeros((0, 128), np.float32)
    d = descriptors.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)  # L1, then the square root: unit L2 rows
    return list(keypoints), np.sqrt(d)


def colmap_uv(keypoints: list[cv2.KeyPoint]) -> np.ndarray:
    """(K,2) float64 keypoint positions in COLMAP's pixel convention (OpenCV's pixel centres are at integers)."""
    return np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2) + 0.5


def colmap_keypoints(keypoints: list[cv2.KeyPoint]) -> np.ndarray:
    """(K,4) float32 rows (x, y, scale, orientation in radians), COLMAP's keypoint form; the scale is
    the detection's sigma (OpenCV's size is its diameter)."""
    if not keypoints:
        return np.zeros((0, 4), np.float32)
    uv = colmap_uv(keypoints)
    extra = np.array([(k.size / 2.0, np.deg2rad(k.angle)) for k in keypoints], dtype=np.float64)
    return np.concatenate([uv, extra], axis=1).astype(np.float32)


def colmap_descriptors(unit: np.ndarray) -> np.ndarray:
    """Unit L1-root float rows -> COLMAP's uint8 encoding (FeatureDescriptorsToUnsignedByte)."""
    return np.minimum(np.round(512.0 * np.asarray(unit, np.float32)), 255.0).astype(np.uint8)
