"""Shared ground-truth cameras and writers for the importer tests."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.core.errors import SceneError, UsvcError
from usvc.core.scene import Camera, Frame, check_rotation
from usvc.prepare.importers import FORMATS, load_scene

SHARED = Path(__file__).resolve().parents[2] / "shared"
X_WORLD = np.array([0.3, -0.2, 1.7])
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


@dataclass
class GtCam:
    """Ground truth: world-to-camera R, t (OpenCV axes) and a COLMAP-convention camera."""

    R: np.ndarray
    t: np.ndarray
    camera: Camera

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def R_cam_to_world(self) -> np.ndarray:
        return self.R.T


def make_gt(seed: int, camera: Camera, depth: float = 4.0) -> GtCam:
    """A random rotation placed so X_WORLD lies in front of the camera, off the optical axis."""
    R = Rotation.random(random_state=seed).as_matrix()
    rng = np.random.default_rng(seed)
    p_cam = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), 1.0]) * depth
    center = X_WORLD - R.T @ p_cam
    return GtCam(R=R, t=-R @ center, camera=camera)


def project(camera: Camera, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """COLMAP's projection for the models the importers produce (distortion included)."""
    x, y, z = R @ X + t
    assert z > 0
    x, y = x / z, y / z
    p = camera.params
    if camera.model == "SIMPLE_RADIAL":
        scale = 1 + p[3] * (x * x + y * y)
        x, y = x * scale, y * scale
    elif camera.model == "OPENCV":
        k1, k2, p1, p2 = p[4:]
        r2 = x * x + y * y
        radial = k1 * r2 + k2 * r2 * r2
        dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        x, y = x + dx, y + dy
    elif camera.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise AssertionError(f"test projection does not cover {camera.model}")
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    return np.array([fx * x + cx, fy * y + cy])


def assert_reprojects(frame: Frame, gt: GtCam) -> None:
    expected = project(gt.camera, gt.R, gt.t, X_WORLD)
    got = project(frame.camera, frame.R, frame.t, X_WORLD)
    np.testing.assert_allclose(got, expected, atol=1e-6, err_msg=frame.name)
    assert (frame.camera.width, frame.camera.height) == (gt.camera.width, gt.camera.height)


def write_image(path: Path, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (width, height), (120, 60, 30)).save(path)


def write_pose_txt(path: Path, T: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in T) + "\n")


def cam_to_world_matrix(gt: GtCam) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = gt.R_cam_to_world, gt.center
    return T
