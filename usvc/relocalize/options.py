"""Options of relocalization (the `relocalize` config group): dense RANSAC-PnP on the predicted
scene coordinates, then refinement: by features (the query's SIFT matched to the map's landmarks,
guided by the learned pose) or keypoint-guided (paper 3.2.2)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from usvc.core.options import in_range, one_of, positive
from usvc.core.precision import PRECISIONS

BACKENDS = ("pycolmap", "opencv", "poselib")
FEATURE_PNP = ("poselib", "pycolmap")  # the feature passes' LO-RANSAC PnP (usvc/relocalize/pnp.py)
REFINE = ("features", "keypoints", "none")
PRIORS = ("learned", "none")  # what guides refinement by features first
EXTRACTORS = ("auto", "opencv", "colmap")  # query SIFT (usvc/relocalize/features/sift.py)
FINAL = ("confirmed", "guided", "images")  # refinement by features' last pass (usvc/relocalize/features/last_pass.py)
REFERENCE_SHORT_SIDE = 480  # ACE's working short side, where its 10 px inlier threshold was tuned
# An inlier threshold above this (px at a 480 px short side, a fifth of it) accepts any pose: every
# cell "agrees" with a pose far off, so confidence says nothing.
MAX_ERROR_PX = 100.0
# The keypoint-guided refinement's values: `refine_<name>` here, `<name>` in RefineOptions
# (usvc/relocalize/keypoint_refinement.py), which is built from them. `refine_problems` is the one rule for both.
REFINE_VALUES = ("radius_px", "max_iterations", "delta", "min_correspondences")


def refine_problems(opts: Any, prefix: str = "") -> list[str]:
    """The refinement's values (`prefix` + each of REFINE_VALUES) must be finite and > 0: T_max = 0
    would never refine, and delta = 0 would never converge."""
    names = [prefix + name for name in REFINE_VALUES]
    out = positive(opts, *names)
    return out + [f"{n}={getattr(opts, n)!r} must be finite" for n in names
                  if getattr(opts, n) > 0 and not math.isfinite(getattr(opts, n))]


@dataclass
class RelocalizeOptions:
    """Relocalization: query -> dense scene coordinates -> RANSAC-PnP, then refinement."""

    backend: str = "opencv"  # RANSAC-PnP solver of the learned pose: opencv | pycolmap | poselib (the default chosen by `python -m benchmarks.accuracy pnp-solvers`)
    max_error_px: float = 10.0  # RANSAC inlier threshold in px of a 480 px short side (ACE's), scaled to the map's working short side
    min_inliers: int = 10  # fewer inliers than this is a failure
    min_confidence: float = 0.1  # answers whose inlier fraction of the cells is lower are failures (docs/confidence.md)
    focal_tolerance: float = 0.25  # given focal length vs the one the map implies: a larger relative gap fails; 0 = no check
    prior: str = "learned"  # refine=features: learned: the learned pose guides matching first, SIFT + PnP's evidence when it leads nowhere | none: no learned pose, SIFT + PnP's registration alone (its SIFT, per-image matches, tracks and PnP: the baseline's answer)
    refine: str = "features"  # features: the query's SIFT matched to the map's landmarks, guided by the learned pose | keypoints: the paper's keypoint-guided refinement (3.2.2) | none; the method group sets it
    refine_radius_px: float = 8.0  # cells within this radius (working-image px) of a projected keypoint form the mask
    refine_max_iterations: int = 5  # T_max
    refine_delta: float = 1e-3  # stop when |dR|_F + |dt| / median scene depth < delta
    refine_min_correspondences: int = 20  # fewer masked cells than this: keep the current pose
    features_extractor: str = "auto"  # query SIFT: auto (COLMAP's on the relocalizer's GPU where pycolmap has CUDA, and with prior=none; else opencv) | opencv (on the CPU, with COLMAP's detector settings: COLMAP's keypoints, most of them, about 4x faster there) | colmap (the landmarks' own extractor, on the grey COLMAP's reader makes; on the GPU where pycolmap has CUDA)
    features_max_keypoints: int = 4096  # refine=features: SIFT keypoints of the query (at the mapping images' short side)
    features_radii_px: list[float] = field(default_factory=lambda: [96.0, 24.0, 8.0])  # search radius of each guided pass, px at a 480 px short side
    features_ratio: float = 0.8  # Lowe's ratio test: nearest descriptor distance < ratio x second nearest
    features_max_error_px: float = 9.0  # LO-RANSAC PnP inlier threshold, px at a 480 px short side (COLMAP's 12 px at 640)
    features_min_inliers: int = 20  # a feature pose needs this many PnP inliers; fewer: fall back to the dense pose
    features_min_inliers_alone: int = 40  # a feature answer from the matches to every landmark (path global, not guided by the learned pose) that the map does not read (confidence < min_confidence) needs this many inliers; fewer: refused, matches by chance give such poses (docs/confidence.md); 0 = no check
    features_pnp: str = "poselib"  # LO-RANSAC PnP of the guided and global passes: poselib (PoseLib's: about half COLMAP's time on their nearly all-inlier matches, the same figures on mini and office, bird's within a query: docs/results.md) | pycolmap (COLMAP's); SIFT + PnP's own evidence keeps COLMAP's, as the baseline registers a query
    features_view_margin_deg: float = 45.0  # landmarks are matched when seen up to this much outside the directions they were mapped from
    features_final: str = "confirmed"  # the answer's last pass: confirmed (each of its matches weighted by the mapping images whose SIFT + PnP matching finds it, unconfirmed ones dropped, refined: at least SIFT + PnP's precision on mini, office and bird) | guided (its guided passes alone, 20-64 ms less a 640 x 480 query) | images (SIFT + PnP's per-image matches instead of its own, refined at 4 px)
    features_retrieval_images: int = 64  # prior=learned: the query's matches to "every landmark" and SIFT + PnP's fallback go to this many mapping photos, those most like it (VLAD over the landmarks' words), and their landmarks; a map with no more photos is searched whole (docs/method.md); 0 = every photo
    features_final_images: int = 32  # the confirmed or images last pass matches at most this many mapping images, those that observe the most of the answer's landmarks (a query's cost then does not grow with the photos that made the map: docs/speed.md); 0 = every one that observes 15 of them
    features_final_comparisons: int = 24_000_000  # the last pass's descriptor comparisons (keypoints x observations compared, summed over its images) at most this many: its images taken most covisible first while they fit, the first always (a dense capture's nearest photos each see all of the query's view: the pass would grow with the capture's density; docs/speed.md); 0 = no bound
    precision: str = "auto"  # encoder and head products: auto (bf16 where native and faster, else fp32) | bf16 | fp32

    def problems(self) -> list[str]:
        out = one_of(self, "backend", BACKENDS) + one_of(self, "precision", PRECISIONS)
        out += one_of(self, "refine", REFINE) + one_of(self, "prior", PRIORS) + one_of(self, "features_extractor", EXTRACTORS)
        out += one_of(self, "features_final", FINAL) + one_of(self, "features_pnp", FEATURE_PNP)
        out += positive(self, "max_error_px", "min_inliers") + refine_problems(self, "refine_")
        out += positive(self, "features_max_keypoints", "features_max_error_px", "features_view_margin_deg")
        for name in ("max_error_px", "features_max_error_px"):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and value > MAX_ERROR_PX:
                out.append(f"{name}={value!r} must be <= {MAX_ERROR_PX:g} (px at a {REFERENCE_SHORT_SIDE} px short "
                           "side; larger thresholds accept any pose)")
        out += in_range(self, "features_ratio", 0.0, 1.0)
        if self.features_min_inliers < 4:
            out.append(f"features_min_inliers={self.features_min_inliers!r} must be >= 4 (a pose needs 4 points)")
        if self.features_retrieval_images < 0:
            out.append(f"features_retrieval_images={self.features_retrieval_images!r} must be >= 0 (0: every photo)")
        if self.features_final_images < 0:
            out.append(f"features_final_images={self.features_final_images!r} must be >= 0 (0: every image)")
        if self.features_final_comparisons < 0:
            out.append(f"features_final_comparisons={self.features_final_comparisons!r} must be >= 0 (0: no bound)")
        if self.features_min_inliers_alone < 0:
            out.append(f"features_min_inliers_alone={self.features_min_inliers_alone!r} must be >= 0 (0: no check)")
        radii = list(self.features_radii_px)
        if not radii or not all(isinstance(r, (int, float)) and 0 < r < float("inf") for r in radii):
            out.append(f"features_radii_px={radii!r} must be one or more positive radii")
        out += in_range(self, "min_confidence", 0.0, 1.0)
        if self.focal_tolerance < 0:
            out.append(f"focal_tolerance={self.focal_tolerance!r} must be >= 0 (0: no check)")
        return out
