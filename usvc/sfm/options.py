"""Options of structure from motion with COLMAP (the `sfm` config group)."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import in_range, non_negative, one_of, positive

EXTRACTORS = ("colmap", "opencv")  # usvc/sfm/opencv_extraction.py
MATCHING = ("auto", "exhaustive", "sequential", "poses", "retrieval")
RECONSTRUCTION = ("auto", "triangulate", "incremental")


@dataclass
class SfmOptions:
    """Structure from motion with COLMAP: SIFT features, matching, then triangulation with the given
    poses held fixed (incremental mapping when the scene has none)."""

    max_num_features: int = 4096  # SIFT features per image
    extractor: str = "colmap"  # SIFT of the mapping images: colmap (COLMAP's own) | opencv (OpenCV's with COLMAP's detector settings, as the query extracts: 2-3x faster)
    matching: str = "auto"  # auto: exhaustive up to exhaustive_max_images, else pose-guided (retrieval without poses) | exhaustive | sequential | poses | retrieval
    exhaustive_max_images: int = 150  # matching=auto: exhaustive matching up to this many images
    sequential_overlap: int = 10  # sequential matching: each image is matched with this many neighbours (retrieval adds them too)
    retrieval_neighbors: int = 20  # retrieval matching: each image with this many most similar images (VLAD on its SIFT)
    retrieval_words: int = 64  # retrieval matching: visual words of the capture's own vocabulary
    pose_pairs_per_image: int = 20  # pose-guided matching: nearest cameras by centre and viewing direction
    keyframe_min_images: int = 200  # posed captures of more mapping frames than this run SfM on keyframes only (usvc/sfm/keyframes.py); smaller ones on every frame
    keyframe_min_translation: float = 0.04  # keyframes: drop a frame nearer than this x the capture's size (median camera distance from their centroid) to a kept keyframe ...; 0 = every frame
    keyframe_min_rotation_deg: float = 2.5  # ... and turned less than this many degrees from it; 0 = every frame
    reconstruction: str = "auto"  # auto: triangulate with the given poses held fixed, incremental when the scene has none | triangulate | incremental
    points_per_problem: int = 1024  # triangulation with poses: the points' bundle adjustment solved in groups of this many points, side by side on the threads (the same model for any count); 0 = COLMAP's point_triangulator as one problem on one thread
    min_points: int = 100  # fewer triangulated points than this is a degenerate scene
    num_threads: int = -1  # COLMAP threads for feature extraction, matching and posed triangulation (the same matches and model for any count); -1 = the top-level threads setting
    seed: int = 0  # COLMAP's RANSAC seed, apart from the mapping seed so mapping seeds reuse the SfM
    verbose: bool = False  # show COLMAP's own per-image log (quiet unless asked)

    def problems(self) -> list[str]:
        out = one_of(self, "matching", MATCHING) + one_of(self, "reconstruction", RECONSTRUCTION)
        out += one_of(self, "extractor", EXTRACTORS)
        out += non_negative(self, "keyframe_min_images", "points_per_problem") + in_range(self, "keyframe_min_translation", 0, float("inf"))
        out += in_range(self, "keyframe_min_rotation_deg", 0, 180)
        return out + positive(self, "max_num_features", "exhaustive_max_images", "sequential_overlap",
                              "pose_pairs_per_image", "retrieval_neighbors", "retrieval_words")
