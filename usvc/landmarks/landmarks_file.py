"""landmarks.h5: the landmarks of one scene (docs/artifacts.md), and the check that a set of
landmarks belongs to a map.

The relocalizer finds a map's landmarks beside it: `landmarks.h5` in the map's folder, else the
pipeline's `../landmarks/landmarks.h5` (data/<scene>/map/map.pt and data/<scene>/landmarks/).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.landmarks.landmark_table import LandmarkObservations, Landmarks, MappingKeypoints

# Version 2 adds the observations (obs/*, images/*), version 3 every keypoint of the mapping images
# (keypoints/*), version 4 stores an observation that is one of those keypoints as its row
# (obs/keypoint) instead of a second copy of its position and descriptor, and the visual words of
# the mapping images (retrieval/words); older files are still read, without what they lack.
LANDMARKS_FORMAT, LANDMARKS_VERSION = "usvc-landmarks", 4
READABLE_VERSIONS = (1, 2, 3, 4)

LANDMARKS_SCHEMA: dict[str, Field] = {
    "xyz": Field("scene units", "position of the landmark: the triangulated SfM point (as in sfm/tracks.h5)", "world"),
    "descriptor": Field("1", "SIFT descriptor standing for the point's track (COLMAP's L1-root SIFT, uint8 "
                             "encoding: 512 x value, clipped at 255); landmarks.descriptor says mean or medoid"),
    "view_dir": Field("1", "unit mean direction from the point to the mapping cameras that saw it", "world"),
    "view_angle_deg": Field("deg", "widest angle between view_dir and the direction to a camera that saw it"),
    "track_length": Field("1", "mapping images that observed the point"),
    "obs/landmark": Field("1", "row of the landmark this observation is of; rows are grouped by obs/image"),
    "obs/image": Field("1", "mapping image of the observation: row of images/*"),
    "obs/uv": Field("px", "the observation's SIFT keypoint; pixel centres at integer+0.5 (COLMAP), x right, y down "
                          "(absent where obs/keypoint is written)", "image"),
    "obs/descriptor": Field("1", "the observation's own SIFT descriptor (COLMAP's, uint8 encoding; absent where "
                                 "obs/keypoint is written)"),
    "obs/keypoint": Field("1", "row of keypoints/* that is the observation (its position and descriptor): written "
                               "instead of obs/uv and obs/descriptor where every observation is one of the keypoints"),
    "images/name": Field("1", "mapping image name, relative to prepared/images"),
    "images/K": Field("px", "intrinsic matrix of the prepared (pinhole) mapping image", "camera->image"),
    "images/size": Field("px", "width, height of the prepared mapping image"),
    "keypoints/image": Field("1", "mapping image of the keypoint: row of images/*; every SIFT keypoint of the "
                                  "mapping images, those that observe no landmark too, grouped by image"),
    "keypoints/uv": Field("px", "SIFT keypoint position; pixel centres at integer+0.5 (COLMAP), x right, y down",
                          "image"),
    "keypoints/descriptor": Field("1", "the keypoint's SIFT descriptor (COLMAP's, uint8 encoding)"),
    "keypoints/landmark": Field("1", "row of the landmark the keypoint observes, -1 for none"),
    "retrieval/words": Field("1", "visual words: k-means centres of the mapping images' unit SIFT descriptors, over "
                                  "which a query's VLAD finds the mapping images most like it"),
}


def write_landmarks(path: Path, landmarks: Landmarks) -> None:
    with write_h5(path, LANDMARKS_SCHEMA, LANDMARKS_FORMAT, LANDMARKS_VERSION) as h5:
        h5.attrs["scene"] = landmarks.scene
        h5.attrs["image_short_side"] = int(landmarks.image_short_side)
        h5["xyz"] = landmarks.xyz
        h5.create_dataset("descriptor", data=landmarks.descriptor, compression="gzip")
        h5["view_dir"], h5["view_angle_deg"] = landmarks.view_dir, landmarks.view_angle_deg
        h5["track_length"] = landmarks.track_length
        if landmarks.words is not None:
            h5["retrieval/words"] = np.asarray(landmarks.words, np.float32)
        obs = landmarks.observations
        if obs is not None:
            h5["obs/landmark"], h5["obs/image"] = obs.landmark, obs.image
            rows = observation_keypoints(obs)
            if rows is not None:  # each observation is one of the keypoints: stored once, there
                h5["obs/keypoint"] = rows
            else:
                h5["obs/uv"] = obs.uv
                h5.create_dataset("obs/descriptor", data=obs.descriptor, compression="gzip")
            h5.create_dataset("images/name", data=np.array(obs.image_names, dtype=object),
                              dtype=h5py.string_dtype())
            h5["images/K"], h5["images/size"] = obs.image_K, obs.image_size
            kp = obs.keypoints
            if kp is not None:
                h5["keypoints/image"], h5["keypoints/uv"], h5["keypoints/landmark"] = kp.image, kp.uv, kp.landmark
                h5.create_dataset("keypoints/descriptor", data=kp.descriptor, compression="gzip")


def observation_keypoints(obs: LandmarkObservations) -> np.ndarray | None:
    """The row of `obs.keypoints` that each observation is (the same image, landmark, position and
    descriptor, bit for bit: the observations and the keypoints that observe a landmark, each sorted
    by image, landmark and position, paired in order), or None where the keypoints are absent or the
    two do not pair so."""
    kp = obs.keypoints
    observing = np.flatnonzero(kp.landmark >= 0) if kp is not None else np.zeros(0, np.int64)
    if kp is None or len(obs.landmark) == 0 or len(observing) != len(obs.landmark):
        return None
    mine = np.lexsort((obs.uv[:, 1], obs.uv[:, 0], obs.landmark, obs.image))
    theirs = observing[np.lexsort((kp.uv[observing, 1], kp.uv[observing, 0], kp.landmark[observing],
                                   kp.image[observing]))]
    rows = np.empty(len(mine), np.int64)
    rows[mine] = theirs
    same = (np.array_equal(kp.image[rows], obs.image) and np.array_equal(kp.landmark[rows], obs.landmark)
            and np.array_equal(kp.uv[rows], obs.uv) and np.array_equal(kp.descriptor[rows], obs.descriptor))
    return rows.astype(np.int32) if same else None


def _observations(h5: h5py.File, path: Path) -> LandmarkObservations | None:
    if "obs" not in h5:
        return None
    names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["images/name"][()]]
    keypoints = _keypoints(h5)
    if "obs/keypoint" in h5:
        if keypoints is None:
            raise UsvcError(f"{path}: landmarks dataset obs/keypoint names rows of keypoints/*, which the file lacks")
        rows = np.asarray(h5["obs/keypoint"][()], np.int64)
        if len(rows) and (rows.min() < 0 or rows.max() >= len(keypoints.image)):
            raise UsvcError(f"{path}: landmarks dataset obs/keypoint names a row outside 0..{len(keypoints.image) - 1}")
        uv, descriptor = keypoints.uv[rows], keypoints.descriptor[rows]
    else:
        uv = np.asarray(h5["obs/uv"][()], np.float32).reshape(-1, 2)
        descriptor = np.asarray(h5["obs/descriptor"][()], np.uint8).reshape(-1, 128)
    return LandmarkObservations(landmark=np.asarray(h5["obs/landmark"][()], np.int32),
                                image=np.asarray(h5["obs/image"][()], np.int32), uv=uv, descriptor=descriptor,
                                image_names=names, image_K=np.asarray(h5["images/K"][()], np.float64),
                                image_size=np.asarray(h5["images/size"][()], np.int32), keypoints=keypoints)


def _keypoints(h5: h5py.File) -> MappingKeypoints | None:
    if "keypoints" not in h5:
        return None
    return MappingKeypoints(image=np.asarray(h5["keypoints/image"][()], np.int32),
                            uv=np.asarray(h5["keypoints/uv"][()], np.float32).reshape(-1, 2),
                            descriptor=np.asarray(h5["keypoints/descriptor"][()], np.uint8).reshape(-1, 128),
                            landmark=np.asarray(h5["keypoints/landmark"][()], np.int32))


# Datasets that hold one row per landmark, observation, mapping image or keypoint, and the columns
# each row has (None: a single value): their declared shapes must agree before any is read.
ROW_TABLES: tuple[dict[str, int | None], ...] = (
    {"xyz": 3, "descriptor": 128, "view_dir": 3, "view_angle_deg": None, "track_length": None},
    {"obs/landmark": None, "obs/image": None, "obs/uv": 2, "obs/descriptor": 128, "obs/keypoint": None},
    {"images/name": None, "images/K": None, "images/size": 2},
    {"keypoints/image": None, "keypoints/uv": 2, "keypoints/descriptor": 128, "keypoints/landmark": None},
    {"retrieval/words": 128},
)


def check_declared_shapes(h5: h5py.File, path: Path) -> None:
    """The datasets of one table declare the same row count and their own columns (from the header:
    nothing is read yet; read_h5 has checked each dataset's declared bytes against the file)."""
    for table in ROW_TABLES:
        rows: tuple[str, int] | None = None
        for name, columns in table.items():
            if name not in h5:
                continue
            ds = h5[name]
            if not isinstance(ds, h5py.Dataset) or not ds.shape:
                raise UsvcError(f"{path}: landmarks dataset {name} is not a table (shape {getattr(ds, 'shape', None)})")
            if columns is not None and (len(ds.shape) != 2 or ds.shape[1] != columns):
                raise UsvcError(f"{path}: landmarks dataset {name} declares shape {ds.shape}, "
                                f"expected ({ds.shape[0]}, {columns}): corrupt or crafted file")
            if rows is None:
                rows = (name, ds.shape[0])
            elif ds.shape[0] != rows[1]:
                raise UsvcError(f"{path}: landmarks dataset {name} declares {ds.shape[0]} rows, {rows[0]} "
                                f"{rows[1]}: corrupt or crafted file")


def read_landmarks(path: Path | str) -> Landmarks:
    path = Path(path)
    with read_h5(path, "landmarks") as h5:
        if h5.attrs.get("format") != LANDMARKS_FORMAT:
            raise UsvcError(f"{path}: not a usvc landmarks file")
        if h5.attrs.get("version") not in READABLE_VERSIONS:
            raise UsvcError(f"{path}: landmarks format version {h5.attrs.get('version')!r}, "
                            f"this code reads {', '.join(map(str, READABLE_VERSIONS))}")
        check_declared_shapes(h5, path)
        scene = h5.attrs.get("scene")
        scene = scene.decode() if isinstance(scene, bytes) else str(scene)
        try:
            return Landmarks(scene=scene, xyz=np.asarray(h5["xyz"][()], np.float64),
                             descriptor=np.asarray(h5["descriptor"][()], np.uint8),
                             view_dir=np.asarray(h5["view_dir"][()], np.float32),
                             view_angle_deg=np.asarray(h5["view_angle_deg"][()], np.float32),
                             track_length=np.asarray(h5["track_length"][()], np.int32),
                             image_short_side=int(h5.attrs.get("image_short_side", 0)),
                             observations=_observations(h5, path),
                             words=np.asarray(h5["retrieval/words"][()], np.float32) if "retrieval/words" in h5
                             else None)
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
