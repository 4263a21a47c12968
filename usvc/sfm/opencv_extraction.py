"""The sfm stage's SIFT with OpenCV (`sfm.extractor=opencv`): each mapping image's keypoints and
descriptors found with the query's detector and descriptor settings (`usvc.core.opencv_sift`:
COLMAP's detector settings, L1-root descriptors; grey by OpenCV's BT.601 conversion) and written into the COLMAP database in COLMAP's form, where matching and
triangulation take them as if COLMAP had extracted them. OpenCV's SIFT is 2.2-3.2x faster than
COLMAP's on one thread (docs/results.md) and finds ~90 % as many keypoints; the images are
extracted side by side on `threads` threads (OpenCV releases Python's lock), each image the same
bits whatever the count."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from usvc.core import opencv_sift
from usvc.core.images import read_image_bgr
from usvc.core.ordered_pool import library_threads


def image_features(path: Path, max_features: int) -> tuple[np.ndarray, np.ndarray]:
    """(K,4) float32 COLMAP keypoints and (K,128) uint8 COLMAP descriptors of one image file."""
    gray = cv2.cvtColor(read_image_bgr(path), cv2.COLOR_BGR2GRAY)
    keypoints, unit = opencv_sift.detect(gray, max_features)
    return opencv_sift.colmap_keypoints(keypoints), opencv_sift.colmap_descriptors(unit)


def write_opencv_features(db_path: Path, image_dir: Path, names: list[str], max_features: int, threads: int) -> int:
    """SIFT of the images `names` (already in the database) into their keypoints and descriptors
    tables; returns the keypoints written. OpenCV's own thread pool is held at one per image."""
    db = pycolmap.Database.open(db_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        missing = [n for n in names if n not in ids]
        if missing:
            raise ValueError(f"images not registered in {db_path}: {missing[:3]}")
        with library_threads(cv2.getNumThreads, cv2.setNumThreads, 1), \
                ThreadPoolExecutor(max_workers=max(1, int(threads)), thread_name_prefix="usvc-sift") as pool:
            found = pool.map(lambda n: image_features(image_dir / n, max_features), names)
            total = 0
            for name, (keypoints, descriptors) in zip(names, found):
                db.write_keypoints(ids[name], keypoints)
                db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                                            descriptors))
                total += len(keypoints)
    finally:
        db.close()
    return total
