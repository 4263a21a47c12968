"""Options of keypoint scoring M(X) >= tau (the `keypoints` config group, paper eq. 1-3)."""

from __future__ import annotations

from dataclasses import dataclass

from usvc.core.options import non_negative, one_of, positive

WEIGHTS = ("uniform", "reprojection")


@dataclass
class KeypointOptions:
    """Keypoints, paper eq. 1-3: M(X) = sum_i w_i exp(-|phi(X) - d_i|^2 / 2 sigma^2), keep M >= tau."""

    tau: float = 1.5  # an SfM point is a keypoint when its score M(X) reaches tau
    sigma: float = 0.15  # kernel bandwidth (L2-normalised SIFT units): a view at the median distance from its track mean (~0.17) counts ~half
    weights: str = "uniform"  # uniform (w_i = 1: M is a soft count of consistent views) | reprojection
    reprojection_scale_px: float = 1.0  # weights=reprojection: w_i = 1 / (1 + (r_i / scale)^2)
    min_track_length: int = 2  # points seen in fewer images are never keypoints

    def problems(self) -> list[str]:
        out = one_of(self, "weights", WEIGHTS) + non_negative(self, "tau")
        return out + positive(self, "sigma", "reprojection_scale_px", "min_track_length")
