"""The canonical in-memory scene every importer produces and every stage consumes.

Conventions (fixed here once, so importers convert and nothing downstream guesses):
- poses are world-to-camera (R, t) in OpenCV/COLMAP camera axes (x right, y down, z forward);
- intrinsics follow COLMAP: the centre of the top-left pixel is at (0.5, 0.5), so a principal
  point "at the image centre" is (W/2, H/2);
- camera models and parameter order are COLMAP's (PINHOLE: fx fy cx cy; OPENCV: fx fy cx cy
  k1 k2 p1 p2; OPENCV_FISHEYE: fx fy cx cy k1 k2 k3 k4; FULL_OPENCV: fx fy cx cy k1 k2 p1 p2 k3 k4 k5
  k6; SIMPLE_RADIAL: f cx cy k; RADIAL: f cx cy k1 k2; SIMPLE_PINHOLE: f cx cy); the prepare stage
  undistorts every distorted model to PINHOLE, so later stages see pinhole cameras only;
- ``metric_scale`` is metres per scene unit, or None when the scene has no metric scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.geometry import camera_centers

CAMERA_MODELS: dict[str, int] = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12,
}
SPLITS = ("train", "test")
# Leading parameters that are focal/principal point; the rest are distortion.
_N_PROJECTION_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4,
                        "OPENCV_FISHEYE": 4, "FULL_OPENCV": 4}


@dataclass(frozen=True)
class Camera:
    """A COLMAP-style camera: model name, image size and parameters in COLMAP's order."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise SceneError(f"unknown camera model {self.model!r}; known: {sorted(CAMERA_MODELS)}")
        if len(self.params) != CAMERA_MODELS[self.model]:
            raise SceneError(
                f"camera model {self.model} takes {CAMERA_MODELS[self.model]} parameters, "
                f"got {len(self.params)}"
            )
        if self.width <= 0 or self.height <= 0:
            raise SceneError(f"camera size must be positive, got {self.width}x{self.height}")
        if not np.all(np.isfinite(self.params)):
            raise SceneError(f"camera parameters are not finite: {self.params}")
        if min(self.focal) <= 0:
            raise SceneError(f"camera focal length must be positive, got {self.focal}")

    @property
    def focal(self) -> tuple[float, float]:
        p = self.params
        return (p[0], p[0]) if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else (p[0], p[1])

    @property
    def principal_point(self) -> tuple[float, float]:
        p = self.params
        return (p[1], p[2]) if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else (p[2], p[3])

    @property
    def K(self) -> np.ndarray:
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """True unless the model is a plain pinhole (a fisheye with zero coefficients still is one)."""
        if self.model == "OPENCV_FISHEYE":
            return True
        return any(abs(v) > 0 for v in self.params[_N_PROJECTION_PARAMS[self.model]:])

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for the image resized to (width, height); distortion is scale-free."""
        sx, sy = width / self.width, height / self.height
        p = list(self.params)
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            if abs(sx - sy) > 1e-3 * max(sx, sy):
                raise SceneError(f"{self.model} has one focal length; cannot scale anisotropically")
            p[0] *= sx
            p[1] *= sx
            p[2] *= sy
        else:
            p[0] *= sx
            p[1] *= sy
            p[2] *= sx
            p[3] *= sy
        return replace(self, width=width, height=height, params=tuple(float(v) for v in p))


def check_rotation(R: np.ndarray, where: str, tol: float = 1e-3) -> None:
    """Reject non-finite or non-rotation matrices with a message naming the frame."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise SceneError(f"{where}: rotation must be 3x3, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise SceneError(f"{where}: pose is not finite")
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise SceneError(
            f"{where}: pose rotation is not a rotation (|RR^T - I| = {err:.2e}, det = {np.linalg.det(R):.3f})"
        )


@dataclass
class Frame:
    """One image with its camera and (optional) world-to-camera pose."""

    name: str
    image_path: Path
    camera: Camera
    split: str
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    depth_path: Path | None = None
    depth_scale: float = 1.0  # depth file value times this = depth in scene units
    focal_known: bool = True  # False: the focal length is a guess for SfM to estimate (no EXIF)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise SceneError(f"{self.name}: split must be one of {SPLITS}, got {self.split!r}")
        if (self.R is None) != (self.t is None):
            raise SceneError(f"{self.name}: pose needs both rotation and translation")
        if self.R is not None:
            self.R = np.asarray(self.R, dtype=np.float64)
            self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
            check_rotation(self.R, f"{self.name}")
            if not np.all(np.isfinite(self.t)):
                raise SceneError(f"{self.name}: pose translation is not finite")

    @property
    def has_pose(self) -> bool:
        return self.R is not None

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        if self.R is None:
            raise SceneError(f"{self.name}: has no pose")
        return camera_centers(self.R, self.t)


@dataclass
class Scene:
    """A set of frames with a split; validated on construction."""

    name: str
    frames: list[Frame]
    metric_scale: float | None = None
    root: Path = field(default_factory=Path)
    pose_source: str = "given"  # "given" by the capture, or "sfm": estimated here (pseudo ground truth)

    def __post_init__(self) -> None:
        if not self.frames:
            raise SceneError(f"scene {self.name!r}: no frames found under {self.root}")
        names = [f.name for f in self.frames]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})[:3]
            raise SceneError(f"scene {self.name!r}: duplicate frame names {dup}")
        posed = {f.has_pose for f in self.frames}
        if len(posed) > 1:
            raise SceneError(f"scene {self.name!r}: some frames have poses and others do not")
        if self.metric_scale is not None and not (self.metric_scale > 0):
            raise SceneError(f"scene {self.name!r}: metric_scale must be > 0, got {self.metric_scale}")

    @property
    def has_poses(self) -> bool:
        return self.frames[0].has_pose

    def split(self, which: str) -> list[Frame]:
        """Frames of one split; an empty split is an error, since every stage needs both."""
        if which not in SPLITS:
            raise SceneError(f"unknown split {which!r}; expected one of {SPLITS}")
        frames = [f for f in self.frames if f.split == which]
        if not frames:
            raise SceneError(f"scene {self.name!r}: the {which!r} split is empty")
        return frames

    def check_images_exist(self) -> None:
        missing = [f.image_path for f in self.frames if not Path(f.image_path).is_file()]
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise SceneError(f"scene {self.name!r}: missing image {missing[0]}{more}")


def every_nth_split(n: int, count: int) -> list[str]:
    """The LLFF/NeRF hold-out rule: index % n == 0 is a query, the rest map."""
    if n < 2:
        raise SceneError(f"split every_nth needs n >= 2, got {n}")
    return ["test" if i % n == 0 else "train" for i in range(count)]
