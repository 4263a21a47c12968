"""Compare two pose sets of the same photos that live in different frames and scales (SfM poses
against imported ground truth): fit a similarity on camera centres, then per-photo errors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg
from usvc.core.scene import Frame


@dataclass(frozen=True)
class Similarity:
    """x_reference = scale * R x_estimate + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def pose(self, R_cam: np.ndarray, t_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A world-to-camera pose of the estimate's frame, expressed in the reference frame."""
        centre = -R_cam.T @ t_cam
        R_new = R_cam @ self.R.T
        return R_new, -R_new @ (self.scale * self.R @ centre + self.t)


@dataclass(frozen=True)
class AlignedErrors:
    """Per-photo errors of ``estimate`` after mapping it into the reference frame."""

    names: list[str]
    rotation_deg: np.ndarray
    center_error: np.ndarray  # in reference units
    scale: float  # reference units per estimate unit
    extent: float  # median distance of the reference centres from their mean
    similarity: Similarity


def align_and_compare(estimate: list[Frame], reference: list[Frame], fit_on: set[str] | None = None) -> AlignedErrors:
    """Similarity reference_from_estimate fitted (least squares, Umeyama) on the camera centres of
    the photos in ``fit_on`` (default: all shared names); errors are reported for every shared photo."""
    ref = {f.name: f for f in reference}
    shared = [f for f in estimate if f.name in ref]
    fit = [f for f in shared if fit_on is None or f.name in fit_on]
    if len(fit) < 3:
        raise UsvcError(f"a similarity needs at least 3 shared posed photos, got {len(fit)}")
    src = np.stack([f.center for f in fit])
    tgt = np.stack([ref[f.name].center for f in fit])
    sim = pycolmap.estimate_sim3d(src, tgt)
    if sim is None:
        raise UsvcError("camera centres are degenerate (collinear?): no similarity")
    R_sim = sim.rotation.matrix()
    centres = np.stack([f.center for f in shared])
    mapped = sim.scale * centres @ R_sim.T + np.asarray(sim.translation)
    ref_c = np.stack([ref[f.name].center for f in shared])
    R_est = np.stack([f.R @ R_sim.T for f in shared])  # cam_from_ref = cam_from_est * est_from_ref
    R_ref = np.stack([ref[f.name].R for f in shared])
    all_ref = np.stack([f.center for f in reference])
    return AlignedErrors(
        names=[f.name for f in shared],
        rotation_deg=np.asarray(rotation_error_deg(R_est, R_ref)),
        center_error=np.linalg.norm(mapped - ref_c, axis=1),
        scale=float(sim.scale),
        extent=float(np.median(np.linalg.norm(all_ref - all_ref.mean(0), axis=1))),
        similarity=Similarity(float(sim.scale), R_sim, np.asarray(sim.translation, dtype=np.float64)),
    )
