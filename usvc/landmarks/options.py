"""Options of the landmarks step (the `landmarks` config group): which SfM points become
landmarks and how each track's descriptors become the landmark's one descriptor."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import non_negative, one_of, positive

DESCRIPTORS = ("mean", "medoid")


@dataclass
class LandmarksOptions:
    """The SfM points as landmarks for feature refinement at query time (relocalize.refine=features)."""

    descriptor: str = "mean"  # one descriptor per point: mean (of the track's unit RootSIFT descriptors, renormalised) | medoid (the track's most central observation)
    min_track_length: int = 2  # points seen in fewer mapping images are left out
    max_error_px: float = 4.0  # points whose mean reprojection error exceeds this are left out (px of the mapping images)
    max_landmarks: int = 0  # keep at most this many (longest tracks first); 0 = all
    retrieval_words: int = 32  # visual words clustered from the mapping photos' SIFT, for finding the mapping photos most like a query (VLAD: relocalize.features_retrieval_images); 0 = none

    def problems(self) -> list[str]:
        out = one_of(self, "descriptor", DESCRIPTORS) + positive(self, "min_track_length", "max_error_px")
        return out + non_negative(self, "max_landmarks", "retrieval_words")
