"""keypoints.h5, the keypoints stage's artifact: its one writer and its one reader.

The kept scene keypoints (SfM points whose descriptors agree across views, `usvc.keypoints.scoring`)
with their track observations, plus the mapping images' cameras, so later stages need only this
file. Every dataset carries units/description/frame attributes (KEYPOINTS_SCHEMA; docs/artifacts.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usvc.core.errors import KeypointError
from usvc.core.h5_file import Field, read_h5, write_h5
from usvc.sfm.tracks_file import IMAGES_SCHEMA, PIXELS, Tracks, write_images_group

KEYPOINTS_FORMAT, KEYPOINTS_VERSION = "usvc-keypoints", 1

KEYPOINTS_SCHEMA: dict[str, Field] = {
    **IMAGES_SCHEMA,
    "keypoints/id": Field("1", "COLMAP point3D id of the kept point (points/id of tracks.h5); rows of "
                               "keypoints/* are the keypoint indices later artifacts use"),
    "keypoints/xyz": Field("scene units", "3D position of the kept keypoint", "world"),
    "keypoints/rgb": Field("1", "keypoint colour R, G, B in 0..255 (COLMAP's)"),
    "keypoints/score": Field("1", "matching score M(X) (paper eq. 1-3): weighted soft count of views whose "
                                  "descriptor agrees with the track mean; kept when >= keypoints.tau"),
    "keypoints/mean_descriptor": Field("1", "phi(X): mean of the track's L2-normalised SIFT descriptors "
                                            "(not renormalised)"),
    "keypoints/track_offset": Field("1", "CSR offsets: the observations of keypoint k are obs/* rows "
                                         "track_offset[k]:track_offset[k+1]; length keypoints + 1"),
    "obs/image": Field("1", "image of the observation: row of images/*"),
    "obs/uv": Field("px", f"measured SIFT position of the observation (from tracks.h5); {PIXELS}", "image"),
}


@dataclass
class Keypoints:
    index: np.ndarray  # rows of the kept points in the tracks
    score: np.ndarray  # (N,) score of every point, kept or not
    mean_descriptor: np.ndarray  # (K,128) of the kept points


@dataclass
class SceneKeypoints:
    """Kept keypoints with their track observations grouped by mapping image name."""

    xyz: np.ndarray  # (K, 3)
    by_image: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (keypoint index (n,), uv (n, 2))


def write_keypoints(path: Path, kp: Keypoints, tracks: Tracks) -> None:
    """Kept points with their observations (image, uv), so later stages need only this file."""
    length = tracks.track_length[kp.index]
    kept = np.zeros(len(tracks.xyz), dtype=bool)
    kept[kp.index] = True
    obs_rows = np.flatnonzero(np.repeat(kept, tracks.track_length))
    with write_h5(path, KEYPOINTS_SCHEMA, KEYPOINTS_FORMAT, KEYPOINTS_VERSION) as h5:
        write_images_group(h5, tracks)
        k = h5.create_group("keypoints")
        k["id"] = tracks.point_id[kp.index]
        k["xyz"] = tracks.xyz[kp.index]
        k["rgb"] = tracks.rgb[kp.index]
        k["score"] = kp.score[kp.index]
        k["mean_descriptor"] = kp.mean_descriptor
        k["track_offset"] = np.concatenate([[0], np.cumsum(length)]).astype(np.int64)
        obs = h5.create_group("obs")
        obs["image"] = tracks.obs_image[obs_rows]
        obs["uv"] = tracks.obs_uv[obs_rows]


def read_scene_keypoints(path: Path) -> SceneKeypoints:
    path = Path(path)
    if not path.is_file():
        raise KeypointError(f"keypoints file not found: {path} (run the keypoints stage first)")
    with read_h5(path, "keypoints") as h5:
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["images/name"][()]]
        xyz = h5["keypoints/xyz"][()].astype(np.float64)
        offset = h5["keypoints/track_offset"][()]
        image, uv = h5["obs/image"][()], h5["obs/uv"][()].astype(np.float64)
    if len(xyz) == 0:
        raise KeypointError(f"{path}: holds no keypoints")
    kp_of_obs = np.repeat(np.arange(len(xyz)), np.diff(offset))
    by_image = {}
    for i, name in enumerate(names):
        rows = np.flatnonzero(image == i)
        by_image[name] = (kp_of_obs[rows], uv[rows])
    return SceneKeypoints(xyz=xyz, by_image=by_image)
