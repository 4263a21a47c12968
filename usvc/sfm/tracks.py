"""Point tracks (every observation of every 3D point, with its SIFT descriptor) as arrays and HDF5.

Layout is CSR: observations of point k are rows offset[k]:offset[k+1] of the obs/* arrays.
uv are in COLMAP pixel coordinates (top-left pixel centre at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pycolmap

from usvc.core.errors import SfmError
from usvc.core.h5_file import Field, read_h5, write_h5


@dataclass
class Tracks:
    image_names: list[str]
    R: np.ndarray  # (M,3,3) world-to-camera of each image
    t: np.ndarray  # (M,3)
    K: np.ndarray  # (M,3,3)
    point_id: np.ndarray  # (N,) COLMAP point3D ids
    xyz: np.ndarray  # (N,3)
    rgb: np.ndarray  # (N,3) uint8
    error: np.ndarray  # (N,) mean reprojection error, px
    offset: np.ndarray  # (N+1,)
    obs_image: np.ndarray  # (T,) index into image_names
    obs_uv: np.ndarray  # (T,2)
    obs_descriptor: np.ndarray  # (T,128) uint8
    obs_error: np.ndarray  # (T,) reprojection error of this observation, px

    @property
    def track_length(self) -> np.ndarray:
        return np.diff(self.offset)

    def point_of_obs(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.xyz)), self.track_length)


def from_reconstruction(rec: pycolmap.Reconstruction, db_path: Path) -> Tracks:
    """Gather tracks image by image (vectorised per image), then sort by point."""
    image_ids = sorted(rec.reg_image_ids())
    id_to_index = {iid: k for k, iid in enumerate(image_ids)}
    pids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    if len(pids) == 0:
        raise SfmError("the reconstruction has no 3D points")
    pid_to_row = {int(p): k for k, p in enumerate(pids)}
    xyz = np.stack([rec.points3D[int(p)].xyz for p in pids])
    rgb = np.stack([rec.points3D[int(p)].color for p in pids]).astype(np.uint8)
    err = np.array([rec.points3D[int(p)].error for p in pids], dtype=np.float32)
    rows, imgs, uvs, descs, errs = [], [], [], [], []
    R, t, K, names = [], [], [], []
    db = pycolmap.Database.open(db_path)
    try:
        for iid in image_ids:
            image = rec.images[iid]
            pose = image.cam_from_world()
            names.append(image.name)
            R.append(pose.rotation.matrix())
            t.append(np.asarray(pose.translation))
            K.append(image.camera.calibration_matrix())
            idx = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
            if len(idx) == 0:
                continue
            pts = image.get_observation_points2D()
            uv = np.array([p.xy for p in pts])
            row = np.array([pid_to_row[p.point3D_id] for p in pts])
            cam_pts = (R[-1] @ xyz[row].T).T + t[-1]
            proj = image.camera.img_from_cam(cam_pts, check_cheirality=False)
            rows.append(row)
            imgs.append(np.full(len(idx), id_to_index[iid], dtype=np.int32))
            uvs.append(uv)
            descs.append(db.read_descriptors(iid).data[idx])
            errs.append(np.linalg.norm(proj - uv, axis=1))
    finally:
        db.close()
    row = np.concatenate(rows)
    order = np.argsort(row, kind="stable")
    counts = np.bincount(row, minlength=len(pids))
    return Tracks(
        image_names=names, R=np.stack(R), t=np.stack(t), K=np.stack(K),
        point_id=pids, xyz=xyz, rgb=rgb, error=err,
        offset=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        obs_image=np.concatenate(imgs)[order], obs_uv=np.concatenate(uvs)[order].astype(np.float32),
        obs_descriptor=np.concatenate(descs)[order].astype(np.uint8),
        obs_error=np.concatenate(errs)[order].astype(np.float32),
    )


TRACKS_FORMAT, TRACKS_VERSION = "usvc-tracks", 1
PIXELS = "pixel centres at integer+0.5 (COLMAP), x right, y down"

# The `images` group of tracks.h5 and keypoints.h5: the registered mapping images.
IMAGES_SCHEMA: dict[str, Field] = {
    "images/name": Field("1", "mapping image name, relative to prepared/images; obs/image indexes these rows"),
    "images/R_world_to_cam": Field(
        "1", "world-to-camera rotation of the registered image: x_cam = R x_world + t, OpenCV camera "
             "axes (x right, y down, z forward)", "world->camera"),
    "images/t_world_to_cam": Field(
        "scene units", "world-to-camera translation: x_cam = R x_world + t (the world origin in camera "
                       "coordinates)", "camera"),
    "images/K": Field("px", f"intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] of the prepared "
                            f"(pinhole) image; {PIXELS}", "camera->image"),
}

TRACKS_SCHEMA: dict[str, Field] = {
    **IMAGES_SCHEMA,
    "points/id": Field("1", "COLMAP point3D id of the point (as in sfm/model/points3D.bin)"),
    "points/xyz": Field("scene units", "triangulated 3D point position", "world"),
    "points/rgb": Field("1", "point colour R, G, B in 0..255 (COLMAP's, from the mapping images)"),
    "points/error": Field("px", "mean reprojection error of the point over its track (COLMAP's)"),
    "points/track_offset": Field("1", "CSR offsets: the observations of point k are obs/* rows "
                                      "track_offset[k]:track_offset[k+1]; length points + 1"),
    "obs/image": Field("1", "image of the observation: row of images/*"),
    "obs/uv": Field("px", f"measured SIFT keypoint position of the observation; {PIXELS}", "image"),
    "obs/error": Field("px", "reprojection error of this observation: distance from the projection of "
                             "points/xyz to obs/uv"),
    "obs/descriptor": Field("1", "SIFT descriptor of the observation (COLMAP's, uint8, 128 values)"),
}


def write_images_group(h5: h5py.File, tracks: Tracks) -> None:
    """The mapping images' names and cameras, shared by every track-derived HDF5."""
    img = h5.create_group("images")
    img.create_dataset("name", data=np.array(tracks.image_names, dtype=object), dtype=h5py.string_dtype())
    img["R_world_to_cam"], img["t_world_to_cam"], img["K"] = tracks.R, tracks.t, tracks.K


def write_tracks(path: Path, tracks: Tracks) -> None:
    """tracks.h5: every dataset carries units/description/frame attributes (TRACKS_SCHEMA)."""
    with write_h5(path, TRACKS_SCHEMA, TRACKS_FORMAT, TRACKS_VERSION) as h5:
        write_images_group(h5, tracks)
        pts = h5.create_group("points")
        pts["id"], pts["xyz"], pts["rgb"], pts["error"] = tracks.point_id, tracks.xyz, tracks.rgb, tracks.error
        pts["track_offset"] = tracks.offset
        obs = h5.create_group("obs")
        obs["image"], obs["uv"], obs["error"] = tracks.obs_image, tracks.obs_uv, tracks.obs_error
        obs.create_dataset("descriptor", data=tracks.obs_descriptor, compression="gzip")


def read_tracks(path: Path) -> Tracks:
    path = Path(path)
    if not path.is_file():
        raise SfmError(f"tracks file not found: {path} (run the sfm stage first)")
    with read_h5(path, "SfM tracks") as h5:
        names = [n.decode() if isinstance(n, bytes) else n for n in h5["images/name"][()]]
        return Tracks(
            image_names=names, R=h5["images/R_world_to_cam"][()], t=h5["images/t_world_to_cam"][()],
            K=h5["images/K"][()], point_id=h5["points/id"][()], xyz=h5["points/xyz"][()],
            rgb=h5["points/rgb"][()], error=h5["points/error"][()], offset=h5["points/track_offset"][()],
            obs_image=h5["obs/image"][()], obs_uv=h5["obs/uv"][()],
            obs_descriptor=h5["obs/descriptor"][()], obs_error=h5["obs/error"][()],
        )


def sfm_stats(tracks: Tracks) -> dict:
    tl = tracks.track_length
    return {
        "images": len(tracks.image_names),
        "points": int(len(tracks.xyz)),
        "observations": int(tl.sum()),
        "mean_track_length": float(tl.mean()),
        "mean_reprojection_error_px": float(tracks.obs_error.mean()),
        "median_reprojection_error_px": float(np.median(tracks.obs_error)),
    }
