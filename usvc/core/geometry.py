"""Pose conversions shared by importers, SfM and evaluation (one definition of each convention).

Quaternions are Hamilton (w, x, y, z); poses are world-to-camera (R, t).
"""

from __future__ import annotations

import numpy as np


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion, normalised; ValueError if it has no direction."""
    w, x, y, z = (float(v) for v in q)
    norm = float(np.sqrt(w * w + x * x + y * y + z * z))
    if not np.isfinite(norm) or norm < 1e-8:
        raise ValueError(f"quaternion ({w}, {x}, {y}, {z}) is not a rotation")
    from scipy.spatial.transform import Rotation  # here: SciPy's spatial module is a quarter second of every start

    return Rotation.from_quat([x / norm, y / norm, z / norm, w / norm]).as_matrix()


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit (w, x, y, z) quaternion of R with the canonical sign w >= 0."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


def camera_centers(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-space camera centres c = -R^T t of world-to-camera poses, (3,) or (N, 3)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", R, t)


def field_of_view_deg(focal: float, side: float) -> float:
    """The field of view (degrees) across an image side of `side` px seen with a `focal` px focal length."""
    return float(np.degrees(2.0 * np.arctan2(side / 2.0, focal)))
