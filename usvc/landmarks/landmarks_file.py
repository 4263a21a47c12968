"""landmarks.h5: the landmarks of one scene (docs/artifacts.md), and the check that a set of
landmarks belongs to a map.

The relocalizer finds a map's landmarks beside it: `landmarks.h5` in the map's folder, else the
pipeline's `../landmarks/landmarks.h5` (data/<scene>/map/map.pt and data/<scene>/landmarks/).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.landmarks.landmark_table import Landmarks

LANDMARKS_FORMAT, LANDMARKS_VERSION = "usvc-landmarks", 1

LANDMARKS_SCHEMA: dict[str, Field] = {
    "xyz": Field("scene units", "position of the landmark: the triangulated SfM point (as in sfm/tracks.h5)", "world"),
    "descriptor": Field("1", "SIFT descriptor standing for the point's track (COLMAP's L1-root SIFT, uint8 "
                             "encoding: 512 x value, clipped at 255); landmarks.descriptor says mean or medoid"),
    "view_dir": Field("1", "unit mean direction from the point to the mapping cameras that saw it", "world"),
    "view_angle_deg": Field("deg", "widest angle between view_dir and the direction to a camera that saw it"),
    "track_length": Field("1", "mapping images that observed the point"),
}


def write_landmarks(path: Path, landmarks: Landmarks) -> None:
    with write_h5(path, LANDMARKS_SCHEMA, LANDMARKS_FORMAT, LANDMARKS_VERSION) as h5:
        h5.attrs["scene"] = landmarks.scene
        h5.attrs["image_short_side"] = int(landmarks.image_short_side)
        h5["xyz"] = landmarks.xyz
        h5.create_dataset("descriptor", data=landmarks.descriptor, compression="gzip")
        h5["view_dir"], h5["view_angle_deg"] = landmarks.view_dir, landmarks.view_angle_deg
        h5["track_length"] = landmarks.track_length


def read_landmarks(path: Path | str) -> Landmarks:
    path = Path(path)
    with read_h5(path, "landmarks") as h5:
        if h5.attrs.get("format") != LANDMARKS_FORMAT:
            raise UsvcError(f"{path}: not a usvc landmarks file")
        if h5.attrs.get("version") != LANDMARKS_VERSION:
            raise UsvcError(f"{path}: landmarks format version {h5.attrs.get('version')!r}, "
                            f"this code reads {LANDMARKS_VERSION}")
        scene = h5.attrs.get("scene")
        scene = scene.decode() if isinstance(scene, bytes) else str(scene)
        try:
            return Landmarks(scene=scene, xyz=np.asarray(h5["xyz"][()], np.float64),
                             descriptor=np.asarray(h5["descriptor"][()], np.uint8),
                             view_dir=np.asarray(h5["view_dir"][()], np.float32),
                             view_angle_deg=np.asarray(h5["view_angle_deg"][()], np.float32),
                             track_length=np.asarray(h5["track_length"][()], np.int32),
                             image_short_side=int(h5.attrs.get("image_short_side", 0)))
        except UsvcError as exc:
            raise UsvcError(f"{path}: {exc}") from None


def landmarks_beside(map_path: Path) -> Path | None:
    """The landmarks file that goes with a map file, if there is one."""
    for candidate in (map_path.parent / LANDMARKS_H5, map_path.parent.parent / "landmarks" / LANDMARKS_H5):
        if candidate.is_file():
            return candidate
    return None


def landmarks_disagree(landmarks: Landmarks, map_scene: object, map_keypoints: np.ndarray | None) -> str:
    """Why these landmarks cannot be the map's ("" when they can). The map's 3D keypoints are SfM
    points of its scene, stored at fp32: landmarks from the same SfM model contain most of them
    exactly (both filters keep well-observed points)."""
    if isinstance(map_scene, str) and map_scene and map_scene != landmarks.scene:
        return f"they are of scene {landmarks.scene!r}, the map of {map_scene!r}"
    if map_keypoints is None or len(map_keypoints) == 0:
        return ""
    mine = {row.tobytes() for row in np.ascontiguousarray(landmarks.xyz.astype(np.float32))}
    theirs = np.ascontiguousarray(np.asarray(map_keypoints, dtype=np.float32))
    shared = sum(row.tobytes() in mine for row in theirs)
    if shared < 0.5 * len(theirs):
        return (f"only {shared} of the map's {len(theirs)} keypoints are among them: "
                "they come from another SfM model than the map")
    return ""
