"""Helpers the format importers share: image listing, matrix and pose conversions, and turning
every bad input into one ``SceneError`` line naming the file at fault."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from usvc.core.errors import SceneError
from usvc.core.exif import oriented_size
from usvc.core.geometry import quat_wxyz_to_matrix
from usvc.core.scene import Camera, Frame, every_nth_split

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")  # any case: .JPG is .jpg


def natural_key(text: str) -> list[Any]:
    """Sort key that orders ``frame2`` before ``frame10`` (numbers compared as numbers)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside ``folder`` in lexicographic order of their names."""
    if not folder.is_dir():
        raise SceneError(f"image folder {folder} does not exist")
    return sorted((p for p in folder.iterdir() if is_image(p)), key=lambda p: p.name)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) as the photo is shown (EXIF orientation applied), from the header only."""
    if not Path(path).is_file():
        raise SceneError(f"missing image {path}")
    return oriented_size(path)


def read_matrix_txt(path: Path) -> np.ndarray:
    """A whitespace-separated numeric text file as a 2-D float array."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SceneError(f"missing file {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: unreadable ({e})") from None
    rows = [line.split() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise SceneError(f"{path}: file is empty")
    if len({len(r) for r in rows}) != 1:
        raise SceneError(f"{path}: rows have different numbers of values")
    try:
        return np.array([[float(v) for v in r] for r in rows], dtype=np.float64)
    except ValueError as e:
        raise SceneError(f"{path}: not a numeric matrix ({e})") from None


def as_matrix(value: Any, shapes: Iterable[tuple[int, int]], where: str, what: str = "pose") -> np.ndarray:
    """Convert nested lists to a float matrix of one of ``shapes`` or fail naming ``where``."""
    shapes = tuple(shapes)
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{where}: {what} is not a numeric matrix") from None
    if m.shape not in shapes:
        raise SceneError(f"{where}: {what} has shape {m.shape}, expected one of {list(shapes)}")
    return m


def world_to_cam_from_cam_to_world(
    R_cam_to_world: np.ndarray, center: np.ndarray, where: str
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) from a camera-to-world rotation and camera centre.

    Uses the transpose rather than a matrix inverse, so a degenerate pose is reported by the
    rotation check in :class:`Frame` instead of a numpy LinAlgError here.
    """
    R_cam_to_world = np.asarray(R_cam_to_world, dtype=np.float64)
    center = np.asarray(center, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(R_cam_to_world)) and np.all(np.isfinite(center))):
        raise SceneError(f"{where}: pose is not finite")
    R = R_cam_to_world.T
    return R, -R @ center


def quat_wxyz_to_R(q: Iterable[float], where: str) -> np.ndarray:
    """Rotation matrix from a (w, x, y, z) quaternion, normalised (files round to ~6 digits)."""
    try:
        return quat_wxyz_to_matrix(np.asarray(list(q), dtype=np.float64))
    except ValueError as e:
        raise SceneError(f"{where}: {e}") from None


def guarded(where: str, build: Callable[[], Any]) -> Any:
    """Run a Camera/Frame constructor and prefix its SceneError with the source file.

    The scene classes name the frame, but the user needs the file that holds the bad value.
    """
    try:
        return build()
    except SceneError as e:
        raise SceneError(f"{where}: {e}") from None


def make_frame(where: str, **kwargs: Any) -> Frame:
    return guarded(where, lambda: Frame(**kwargs))


def make_camera(where: str, model: str, width: int, height: int, params: Iterable[float]) -> Camera:
    return guarded(where, lambda: Camera(model, int(width), int(height), tuple(float(p) for p in params)))


def assign_splits(
    count: int,
    split_rule: str,
    split_n: int,
    given: list[str] | None,
    scene_name: str,
    fmt: str,
) -> list[str]:
    """Split labels for frames already in the format's canonical order.

    ``given`` is the format's own split (None when the format has none), which is an error
    for ``split_rule == "given"`` so a scene is never silently split by a default rule.
    """
    if split_rule == "every_nth":
        return every_nth_split(split_n, count)
    if given is None:
        raise SceneError(
            f"scene {scene_name!r}: format {fmt!r} has no train/test split of its own; "
            f"use split_rule='every_nth'"
        )
    return given
