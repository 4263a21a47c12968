"""Point tracks (every observation of every 3D point, with its SIFT descriptor) as arrays and HDF5.

Layout is CSR: observations of point k are rows offset[k]:offset[k+1] of the obs/* arrays.
uv are in COLMAP pixel coordinates (top-left pixel centre at (0.5, 0.5)).

The median scene depth is the scale that makes translation errors scale-free: scenes without a
metric scale (COLMAP units) cannot be scored in centimetres, so their translation accuracy is
judged relative to how far the cameras typically look (`acc_5deg_3pct`: error below 3 % of this
depth). It is measured where the map was built (every observation of every SfM point, in the
camera that observed it), computed once when tracks.h5 is written and stored as its `median_depth`
attribute (`read_median_depth`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pycolmap

from usvc.core.errors import SfmError, UsvcError
from usvc.core.h5_file import Field, read_h5, write_h5


@dataclass
class Tracks:
    """The registered images and their tracks; `R`, `t` are world-to-camera (x_cam = R x_world + t)."""

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
    # every SIFT keypoint of the images, grouped by image (absent in files before version 2)
    kp_image: np.ndarray | None = None  # (K,) index into image_names
    kp_uv: np.ndarray | None = None  # (K,2) float32
    kp_descriptor: np.ndarray | None = None  # (K,128) uint8
    kp_point: np.ndarray | None = None  # (K,) int64 row of the point the keypoint observes, -1 for none

    @property
    def track_length(self) -> np.ndarray:
        return np.diff(self.offset)

    def point_of_obs(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.xyz)), self.track_length)


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
    kp_img, kp_uv, kp_desc, kp_point = [], [], [], []
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
            every = db.read_descriptors(iid).data
            keypoints = db.read_keypoints(iid)[:, :2]
            if len(keypoints) != image.num_points2D():
                raise SfmError(f"image {image.name!r}: {len(keypoints)} keypoints in the database, "
                               f"{image.num_points2D()} in the model")
            kp_img.append(np.full(len(keypoints), id_to_index[iid], dtype=np.int32))
            kp_uv.append(np.asarray(keypoints, np.float32))
            kp_desc.append(np.asarray(every, np.uint8).reshape(-1, 128))
            point_of = np.full(len(keypoints), -1, dtype=np.int64)
            if len(idx) == 0:
                kp_point.append(point_of)
                continue
            pts = image.get_observation_points2D()
            uv = np.array([p.xy for p in pts])
            row = np.array([pid_to_row[p.point3D_id] for p in pts])
            point_of[idx] = row
            kp_point.append(point_of)
            cam_pts = (R[-1] @ xyz[row].T).T + t[-1]
            proj = image.camera.img_from_cam(cam_pts, check_cheirality=False)
            rows.append(row)
            imgs.append(np.full(len(idx), id_to_index[iid], dtype=np.int32))
            uvs.append(uv)
            descs.append(every[idx])
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
        kp_image=np.concatenate(kp_img), kp_uv=np.concatenate(kp_uv).reshape(-1, 2),
        kp_descriptor=np.concatenate(kp_desc).reshape(-1, 128), kp_point=np.concatenate(kp_point),
    )


# Version 2 adds every keypoint of the images (keypoints/*); version 1 files are still read, without them.
TRACKS_FORMAT, TRACKS_VERSION = "usvc-tracks", 2
MEDIAN_DEPTH_ATTR = "median_depth"  # file attribute: median_scene_depth of the tracks
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
    "keypoints/image": Field("1", "image of the keypoint: row of images/*; every SIFT keypoint of the images, "
                                  "grouped by image in the database's order"),
    "keypoints/uv": Field("px", f"SIFT keypoint position; {PIXELS}", "image"),
    "keypoints/descriptor": Field("1", "SIFT descriptor of the keypoint (COLMAP's, uint8, 128 values)"),
    "keypoints/point": Field("1", "row of points/* the keypoint observes, -1 for none"),
}


def write_images_group(h5: h5py.File, tracks: Tracks) -> None:
    """The mapping images' names and cameras, shared by every track-derived HDF5."""
    img = h5.create_group("images")
    img.create_dataset("name", data=np.array(tracks.image_names, dtype=object), dtype=h5py.string_dtype())
    img["R_world_to_cam"], img["t_world_to_cam"], img["K"] = tracks.R, tracks.t, tracks.K


def write_tracks(path: Path, tracks: Tracks) -> None:
    """tracks.h5: every dataset carries units/description/frame attributes (TRACKS_SCHEMA); the file
    attribute `median_depth` is `median_scene_depth(tracks)` (absent when no observation has a
    positive depth: `read_median_depth` then raises as the computation does)."""
    try:
        median_depth = median_scene_depth(tracks)
    except UsvcError:
        median_depth = None
    with write_h5(path, TRACKS_SCHEMA, TRACKS_FORMAT, TRACKS_VERSION) as h5:
        if median_depth is not None:
            h5.attrs[MEDIAN_DEPTH_ATTR] = np.float64(median_depth)
        write_images_group(h5, tracks)
        pts = h5.create_group("points")
        pts["id"], pts["xyz"], pts["rgb"], pts["error"] = tracks.point_id, tracks.xyz, tracks.rgb, tracks.error
        pts["track_offset"] = tracks.offset
        obs = h5.create_group("obs")
        obs["image"], obs["uv"], obs["error"] = tracks.obs_image, tracks.obs_uv, tracks.obs_error
        obs.create_dataset("descriptor", data=tracks.obs_descriptor, compression="gzip")
        if tracks.kp_image is not None:
            kp = h5.create_group("keypoints")
            kp["image"], kp["uv"], kp["point"] = tracks.kp_image, tracks.kp_uv, tracks.kp_point
            kp.create_dataset("descriptor", data=tracks.kp_descriptor, compression="gzip")


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
            **({"kp_image": h5["keypoints/image"][()], "kp_uv": h5["keypoints/uv"][()],
                "kp_descriptor": h5["keypoints/descriptor"][()], "kp_point": h5["keypoints/point"][()]}
               if "keypoints" in h5 else {}),
        )


def read_median_depth(path: Path) -> float:
    """The median scene depth of tracks.h5 `path` (scene units): its `median_depth` attribute, or
    for a file written before the attribute existed, `median_scene_depth` of its tracks (the same
    float)."""
    path = Path(path)
    if not path.is_file():
        raise SfmError(f"tracks file not found: {path} (run the sfm stage first)")
    with read_h5(path, "SfM tracks") as h5:
        stored = h5.attrs.get(MEDIAN_DEPTH_ATTR)
    return float(stored) if stored is not None else median_scene_depth(read_tracks(path))


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
