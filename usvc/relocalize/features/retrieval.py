"""The mapping photos most like a query, found by retrieval: the query's VLAD vector (its SIFT
descriptors over the map's own visual words, `landmarks.retrieval_words`) against each mapping
photo's. The query's matches to "every landmark" and SIFT + PnP's per-image matching (the
fallback) then touch only those photos and the landmarks they observe
(`relocalize.features_retrieval_images`), so their cost is bounded whatever the size of the map.
A map with no more photos than that, or landmarks without words (older files), is searched whole,
as before."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usvc.core.vlad import vlad
from usvc.landmarks.landmark_table import Landmarks, image_descriptors, unit_descriptors
from usvc.relocalize.features.sift import QueryFeatures


@dataclass(frozen=True)
class Retrieved:
    """What a query is matched against: the rows of the mapping images and of the landmarks they
    observe (both sorted), or None for every one."""

    images: np.ndarray | None = None
    landmarks: np.ndarray | None = None

    def record(self) -> dict | None:
        return None if self.images is None else {"images": int(len(self.images)),
                                                  "landmarks": int(len(self.landmarks))}


class ImageRetrieval:
    """The map's mapping photos as VLAD vectors over its words, made on first use (once per map)."""

    def __init__(self, landmarks: Landmarks) -> None:
        self.landmarks = landmarks
        obs = landmarks.observations
        self.images = 0 if obs is None else len(obs.image_names)
        self._codes: np.ndarray | None = None
        # each image's observations (rows of obs), so a query's landmarks cost its photos' observations only
        self._slices = {} if obs is None else {image: (a, b) for image, a, b in obs.image_slices()}

    @property
    def available(self) -> bool:
        return self.landmarks.words is not None and self.landmarks.observations is not None and self.images > 0

    def codes(self) -> np.ndarray:
        """(M, W * 128) the mapping photos' VLAD vectors."""
        if self._codes is None:
            words = self.landmarks.words
            assert words is not None and self.landmarks.observations is not None
            self._codes = np.stack([vlad(d, words) for d in image_descriptors(self.landmarks.observations)])
        return self._codes

    def retrieve(self, feats: QueryFeatures, k: int) -> Retrieved:
        """The `k` mapping photos most like the query (largest VLAD similarity, the first in image
        order on ties) and the landmarks they observe; every one (None) where `k` is 0, the map has
        no more than `k` photos, or no words."""
        if k <= 0 or not self.available or self.images <= k:
            return Retrieved()
        words = self.landmarks.words
        assert words is not None and self.landmarks.observations is not None
        query = vlad(unit_descriptors(feats.codes), words)
        similarity = self.codes() @ query
        images = np.sort(np.lexsort((np.arange(self.images), -similarity))[:k])
        observed = self.landmarks.observations.landmark
        seen = np.zeros(len(self.landmarks.xyz), bool)  # a mask, not a sort of the observations: sorted rows alike
        for i in images:
            if i in self._slices:
                seen[observed[slice(*self._slices[i])]] = True
        return Retrieved(images.astype(np.int64), np.flatnonzero(seen).astype(np.int64))
