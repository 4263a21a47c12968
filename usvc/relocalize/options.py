"""Options of relocalization (the `relocalize` config group): dense RANSAC-PnP on the predicted
scene coordinates, then keypoint-guided refinement (paper 3.2.2)."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import in_range, one_of, positive
from usvc.core.precision import PRECISIONS

BACKENDS = ("pycolmap", "opencv")
REFERENCE_SHORT_SIDE = 480  # ACE's working short side, where its 10 px inlier threshold was tuned


@dataclass
class RelocalizeOptions:
    backend: str = "opencv"  # RANSAC-PnP solver: opencv | pycolmap
    max_error_px: float = 10.0  # RANSAC inlier threshold in px of a 480 px short side, scaled to the working size
    min_inliers: int = 10  # fewer inliers than this is a failure
    min_confidence: float = 0.1  # answers whose inlier fraction of the cells is lower are failures (docs/confidence.md)
    focal_tolerance: float = 0.25  # given focal length vs the one the map implies: a larger relative gap fails; 0 = no check
    refine: bool = True  # keypoint-guided iterative refinement (paper 3.2.2); maps without keypoints skip it
    refine_radius_px: float = 8.0  # cells within this radius (working-image px) of a projected keypoint form the mask
    refine_max_iterations: int = 5  # T_max
    refine_delta: float = 1e-3  # stop when |dR|_F + |dt| / median scene depth < delta
    refine_min_correspondences: int = 20  # fewer masked cells than this: keep the current pose
    precision: str = "auto"  # encoder and head products: auto (bf16 where native and faster, else fp32) | bf16 | fp32

    def problems(self) -> list[str]:
        out = one_of(self, "backend", BACKENDS) + one_of(self, "precision", PRECISIONS)
        out += positive(self, "max_error_px", "min_inliers", "refine_radius_px", "refine_max_iterations",
                        "refine_delta", "refine_min_correspondences")
        out += in_range(self, "min_confidence", 0.0, 1.0)
        if self.focal_tolerance < 0:
            out.append(f"focal_tolerance={self.focal_tolerance!r} must be >= 0 (0: no check)")
        return out
