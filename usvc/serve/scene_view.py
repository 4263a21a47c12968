"""GET /v1/maps/{name}/scene: what the page draws around a localized camera.

A map's 3D points, evenly strided down to at most `MAX_POINTS` (its landmarks, else the map file's
3D keypoints, else the SfM points of the scene it was made from), and the mapping cameras (centre,
viewing direction, image name) where the scene's SfM files lie beside the map (`sfm/tracks.h5` or
`keypoints/keypoints.h5` of the map's scene folder, or one of them in the map's own folder). The
answer is computed once per map and kept as JSON bytes; coordinates are rounded to `DECIMALS`.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from usvc.core.artifact_names import KEYPOINTS_H5, TRACKS_H5
from usvc.core.geometry import camera_centers
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize.answer_checks import map_extent
from usvc.relocalize.relocalizer import Relocalizer

log = logging.getLogger(__name__)

MAX_POINTS = 20_000  # what a browser draws smoothly in WebGL, and a few hundred kB of JSON
MAX_CAMERAS = 2_000
DECIMALS = 4


@dataclass
class MappingCameras:
    """The mapping images' cameras: world-space centres, unit viewing directions (the camera's +z)
    and unit "up" directions (its -y, OpenCV axes), in the file's image order."""

    names: list[str]
    centers: np.ndarray  # (M,3)
    forward: np.ndarray  # (M,3)
    up: np.ndarray  # (M,3)
    source: str  # the file's name


def strided(rows: np.ndarray, limit: int) -> np.ndarray:
    """At most `limit` rows, evenly strided from the first (deterministic: the same rows every time)."""
    if limit < 1:
        raise ValueError(f"limit must be positive, got {limit}")
    step = max(1, -(-len(rows) // limit))
    return rows[::step]


def camera_files(map_path: Path) -> list[Path]:
    """Where the mapping cameras of the map at `map_path` may be: its scene folder's SfM tracks and
    kept keypoints (a map at `<scene>/map/map.pt`), or the same files beside the map."""
    scene = ScenePaths.of_scene_dir(map_path.parent.parent)
    return [scene.tracks_file, scene.keypoints_file, map_path.parent / TRACKS_H5, map_path.parent / KEYPOINTS_H5]


def read_cameras(path: Path) -> MappingCameras:
    """The `images` group (name, R_world_to_cam, t_world_to_cam) of a tracks.h5 or keypoints.h5."""
    with h5py.File(path, "r") as h5:
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["images/name"][()]]
        R = np.asarray(h5["images/R_world_to_cam"][()], dtype=np.float64).reshape(-1, 3, 3)
        t = np.asarray(h5["images/t_world_to_cam"][()], dtype=np.float64).reshape(-1, 3)
    if not (len(names) == len(R) == len(t)):
        raise ValueError(f"{len(names)} names, {len(R)} rotations and {len(t)} translations")
    keep = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    R, t = R[keep], t[keep]
    names = [n for n, k in zip(names, keep) if k]
    # x_cam = R x_world + t: the camera's axes in the world are R's rows
    return MappingCameras(names, camera_centers(R, t), R[:, 2, :], -R[:, 1, :], path.name)


def mapping_cameras(map_path: Path, known: list[str] | None = None) -> MappingCameras | None:
    """The mapping cameras from the first readable file of `camera_files`, or None. `known`: the
    mapping images the map's landmarks name, when it has them: a file that shares none of them is
    another scene's, and passed over."""
    for path in camera_files(map_path):
        if not path.is_file():
            continue
        try:
            found = read_cameras(path)
        except (OSError, KeyError, ValueError) as exc:
            log.warning("mapping cameras of %s: %s is unreadable (%s)", map_path, path, exc)
            continue
        if known and not set(known) & set(found.names):
            log.warning("mapping cameras of %s: %s names none of its landmarks' images", map_path, path)
            continue
        return found
    return None


def sfm_points(map_path: Path) -> np.ndarray | None:
    """The SfM points (`points/xyz` of the scene's tracks.h5), for a map without landmarks or keypoints."""
    for path in camera_files(map_path):
        if path.name != TRACKS_H5 or not path.is_file():
            continue
        try:
            with h5py.File(path, "r") as h5:
                return np.asarray(h5["points/xyz"][()], dtype=np.float64).reshape(-1, 3)
        except (OSError, KeyError, ValueError) as exc:
            log.warning("SfM points of %s: %s is unreadable (%s)", map_path, path, exc)
    return None


def map_points(relocalizer: Relocalizer) -> tuple[np.ndarray, str]:
    """The map's 3D points and where they come from: its landmarks, else the map file's 3D
    keypoints, else the scene's SfM points; (0,3) and "none" without any."""
    if relocalizer.landmarks is not None and len(relocalizer.landmarks.xyz):
        return np.asarray(relocalizer.landmarks.xyz, dtype=np.float64), "landmarks"
    if relocalizer.keypoints_xyz is not None and len(relocalizer.keypoints_xyz):
        return np.asarray(relocalizer.keypoints_xyz, dtype=np.float64), "map keypoints"
    found = sfm_points(relocalizer.map_path)
    if found is not None and len(found):
        return found, "sfm points"
    return np.zeros((0, 3)), "none"


def _rounded(values: np.ndarray) -> list[Any]:
    return np.round(np.asarray(values, dtype=np.float64), DECIMALS).tolist()


def unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return v / n if np.isfinite(n) and n > 1e-12 else None


def scene_record(name: str, relocalizer: Relocalizer, max_points: int = MAX_POINTS,
                 max_cameras: int = MAX_CAMERAS) -> dict[str, Any]:
    """The scene endpoint's answer for map `name`: points as x, y, z lists (strided), their total
    and source, the map's centre and radius (`map_extent`), the mapping cameras (strided) and the
    world's mean "up" of those cameras (None without cameras)."""
    xyz, source = map_points(relocalizer)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    shown = strided(xyz, max_points)
    extent = map_extent(xyz)
    observations = relocalizer.landmarks.observations if relocalizer.landmarks is not None else None
    cams = mapping_cameras(relocalizer.map_path, None if observations is None else observations.image_names)
    cameras: dict[str, Any] = {"total": 0, "source": None, "names": [], "centers": [], "forward": []}
    up = None
    if cams is not None and len(cams.names):
        rows = strided(np.arange(len(cams.names)), max_cameras)
        cameras = {"total": len(cams.names), "source": cams.source, "names": [cams.names[i] for i in rows],
                   "centers": _rounded(cams.centers[rows]), "forward": _rounded(cams.forward[rows])}
        mean_up = unit(cams.up.mean(axis=0))
        up = None if mean_up is None else _rounded(mean_up)
        if extent is None:  # no points: the cameras give the scale
            extent = map_extent(cams.centers)
    return {
        "name": name,
        "points": {"total": int(len(xyz)), "shown": int(len(shown)), "source": source,
                   "x": _rounded(shown[:, 0]), "y": _rounded(shown[:, 1]), "z": _rounded(shown[:, 2])},
        "center": None if extent is None else _rounded(extent[0]),
        "radius": None if extent is None else round(float(extent[1]), DECIMALS),
        "cameras": cameras,
        "up": up,
    }


class SceneCache:
    """Each map's scene answer as JSON bytes, computed on first request and then kept."""

    def __init__(self) -> None:
        self._done: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def get(self, name: str, relocalizer: Relocalizer) -> bytes:
        with self._lock:  # one computation per map, even under concurrent first requests
            if name not in self._done:
                self._done[name] = json.dumps(scene_record(name, relocalizer), separators=(",", ":")).encode()
            return self._done[name]
