"""Image pairs for an unposed capture too large to match exhaustively, found by retrieval.

File order says nothing about which photos overlap when two phones, an export or a shuffle named
them, so the pairs come from the photos' content: a VLAD vector per image from its own SIFT
descriptors (already in COLMAP's database), over a vocabulary of `retrieval_words` visual words
clustered from the capture itself (seeded k-means on a sample of its descriptors), and each image
is paired with its `retrieval_neighbors` most similar images. Pairs of images next to each other
in name order (`sequential_overlap` of them) are added too, which costs little and keeps what a
sequential capture's order tells. Nothing is fetched: the vocabulary is the capture's own.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.vlad import vlad, vocabulary

log = logging.getLogger(__name__)


def _rows(descriptors) -> np.ndarray:
    """A database's descriptors as an array (pycolmap 4 wraps them in FeatureDescriptors)."""
    return descriptors.data if hasattr(descriptors, "data") else descriptors


def _descriptors(db_path: Path) -> tuple[list[str], list[np.ndarray]]:
    """(names in image-id order, each image's RootSIFT descriptors as float32 rows)."""
    db = pycolmap.Database.open(db_path)
    try:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        out = []
        for im in images:
            d = np.asarray(_rows(db.read_descriptors(im.image_id)), dtype=np.float32).reshape(-1, 128)
            d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))  # RootSIFT: Hellinger kernel
            out.append(d)
        return [im.name for im in images], out
    finally:
        db.close()


def retrieval_pairs(db_path: Path, neighbors: int, overlap: int, words: int, seed: int) -> list[tuple[str, str]]:
    """Each image with its `neighbors` most similar images (VLAD over the capture's own vocabulary)
    and its `overlap` next images in name order; every pair once, as (lower id, higher id), sorted."""
    names, descriptors = _descriptors(db_path)
    n = len(names)
    if n < 2:
        return []
    centres = vocabulary(descriptors, words, seed)
    codes = np.stack([vlad(d, centres) for d in descriptors])
    similarity = codes @ codes.T
    np.fill_diagonal(similarity, -np.inf)
    pairs: set[tuple[int, int]] = set()
    k = min(neighbors, n - 1)
    for i in range(n):
        # most similar first; ties by image id, so the draw does not depend on the sort's whims
        order = np.lexsort((np.arange(n), -similarity[i]))[:k]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in order)
        pairs.update((i, j) for j in range(i + 1, min(n, i + 1 + overlap)))
    log.info("retrieval: %d pairs for %d images (%d neighbours each, %d in name order, %d words)", len(pairs), n, k,
             overlap, len(centres))
    return [(names[i], names[j]) for i, j in sorted(pairs)]
