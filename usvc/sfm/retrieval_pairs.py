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
from scipy.cluster.vq import kmeans2

log = logging.getLogger(__name__)

_SAMPLE_PER_IMAGE = 256  # descriptors per image drawn for the vocabulary
_SAMPLE_MAX = 65_536  # descriptors in all for the vocabulary


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


def vocabulary(descriptors: list[np.ndarray], words: int, seed: int) -> np.ndarray:
    """`words` cluster centres of a seeded sample of the descriptors (the same draw for a given seed)."""
    rng = np.random.default_rng(seed)
    per_image = min(_SAMPLE_PER_IMAGE, max(1, _SAMPLE_MAX // max(1, len(descriptors))))
    sample = [d[np.sort(rng.choice(len(d), size=min(per_image, len(d)), replace=False))] for d in descriptors if len(d)]
    data = np.concatenate(sample).astype(np.float64)
    words = min(words, len(data))
    centres, _ = kmeans2(data, words, iter=20, minit="++", seed=rng)
    return centres.astype(np.float32)


def vlad(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """The image's VLAD vector: residuals summed per nearest word, each word's block L2-normalised
    (intra-normalisation), signed square root, then L2-normalised as a whole."""
    out = np.zeros_like(centres)
    if len(descriptors):
        d2 = (descriptors ** 2).sum(1)[:, None] - 2 * descriptors @ centres.T + (centres ** 2).sum(1)[None]
        nearest = np.argmin(d2, axis=1)
        np.add.at(out, nearest, descriptors - centres[nearest])
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    out = out.reshape(-1)
    out = np.sign(out) * np.sqrt(np.abs(out))
    return out / max(float(np.linalg.norm(out)), 1e-12)


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
