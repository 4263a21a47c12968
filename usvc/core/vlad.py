"""VLAD image descriptors over a vocabulary of visual words clustered from the capture itself:
what finds the photos most alike, for SfM's pairs of an unposed capture (`usvc.sfm.retrieval_pairs`)
and for the mapping views a query is matched against (`usvc.relocalize.features.retrieval`). Nothing
is fetched: the words are the capture's own SIFT descriptors, clustered by seeded k-means."""

from __future__ import annotations

import numpy as np
from scipy.cluster.vq import kmeans2

_SAMPLE_PER_IMAGE = 256  # descriptors per image drawn for the vocabulary
_SAMPLE_MAX = 65_536  # descriptors in all for the vocabulary


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
