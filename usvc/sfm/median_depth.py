"""Median scene depth from the SfM tracks: the scale that makes translation errors scale-free.

Scenes without a metric scale (COLMAP units) cannot be scored in centimetres, so their
translation accuracy is judged relative to how far the cameras typically look
(`acc_5deg_3pct`: error below 3 % of this depth). The depth is measured where the map was
built: every observation of every SfM point, in the camera that observed it.
"""

from __future__ import annotations

import numpy as np

from usvc.core.errors import UsvcError
from usvc.sfm.tracks import Tracks


def observation_depths(tracks: Tracks) -> np.ndarray:
    """z-depth (R_img @ X + t)[2] of each observation's point in its observing camera, (T,)."""
    point = tracks.point_of_obs()
    image = np.asarray(tracks.obs_image, dtype=np.int64)
    if len(point) != len(image):
        raise UsvcError(f"tracks: {len(image)} observations but track offsets count {len(point)}")
    # Only the third row of each rotation matters; gathering (T,3) rows instead of (T,3,3)
    # matrices keeps memory at a third for scenes with millions of observations.
    r_z = np.asarray(tracks.R, dtype=np.float64)[image, 2, :]
    t_z = np.asarray(tracks.t, dtype=np.float64)[image, 2]
    return np.einsum("ij,ij->i", r_z, np.asarray(tracks.xyz, dtype=np.float64)[point]) + t_z


def median_scene_depth(tracks: Tracks) -> float:
    """Median depth over observations in front of their camera, in scene units.

    Observations behind the camera (z <= 0) are SfM outliers and are left out rather than
    allowed to pull the median towards zero.
    """
    z = observation_depths(tracks)
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        raise UsvcError(
            f"tracks: no observation has a positive depth ({len(tracks.obs_image)} observations of "
            f"{len(tracks.xyz)} points); cannot compute the median scene depth"
        )
    return float(np.median(z))
