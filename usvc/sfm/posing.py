"""Poses for a scene that has none: COLMAP incremental SfM on the mapping photos, then each query
registered against that model on its own, so the queries get pseudo ground truth while nothing of
theirs enters the reconstruction (and so the map).

The reconstruction's frame and scale become the scene's. Cameras come out calibrated (focal
length and SIMPLE_RADIAL distortion refined by bundle adjustment); the prepare stage then
undistorts the photos with them like any distorted capture. Photos that cannot be posed are
reported with a one-line reason each, and a scene where fewer than half are posed is an error; so is
a reconstruction whose strongly matching photo pairs contradict their poses (`registration_check`:
a run of photos registered on the wrong side of a symmetric object).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.errors import SfmError
from usvc.core.scene import Camera, Frame, Scene
from usvc.sfm.reconstruction import (
    MIN_MAPPING_IMAGES,
    SfmOptions,
    extract,
    match,
    pipeline_options,
)
from usvc.sfm.registration_check import check_registration

log = logging.getLogger(__name__)

MIN_QUERY_INLIERS = 20  # 2D-3D inliers for a query's pose to count as ground truth
QUERY_MAX_ERROR_PX = 4.0  # RANSAC threshold at the working resolution


def _camera(cam: pycolmap.Camera) -> Camera:
    return Camera(cam.model.name, int(cam.width), int(cam.height), tuple(float(v) for v in cam.params))


def _correspondences(db: pycolmap.Database, rec: pycolmap.Reconstruction, query_id: int,
                     mapped: dict[int, pycolmap.Image]) -> tuple[np.ndarray, np.ndarray]:
    """2D keypoints of the query matched (geometrically verified) to triangulated points."""
    keypoints = db.read_keypoints(query_id)
    p2, p3 = [], []
    for image_id, image in mapped.items():
        if not db.exists_two_view_geometry(query_id, image_id):
            continue
        matches = db.read_two_view_geometry(query_id, image_id).inlier_matches
        for q, m in matches:
            point = image.points2D[int(m)]
            if point.has_point3D():
                p2.append(keypoints[int(q), :2])
                p3.append(rec.points3D[point.point3D_id].xyz)
    return np.array(p2, dtype=np.float64).reshape(-1, 2), np.array(p3, dtype=np.float64).reshape(-1, 3)


def register_query(db: pycolmap.Database, rec: pycolmap.Reconstruction, query_id: int,
                   mapped: dict[int, pycolmap.Image], camera: pycolmap.Camera, seed: int
                   ) -> tuple[np.ndarray, np.ndarray, int, str]:
    """(R, t, inliers, why) of one query from its verified matches to the model's points; `why`
    says why it was not posed (then R and t are empty)."""
    p2, p3 = _correspondences(db, rec, query_id, mapped)
    if len(p2) < MIN_QUERY_INLIERS:
        return (np.empty(0), np.empty(0), 0,
                f"only {len(p2)} matches to reconstructed points (need {MIN_QUERY_INLIERS})")
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = QUERY_MAX_ERROR_PX
    est.ransac.random_seed = seed
    ref = pycolmap.AbsolutePoseRefinementOptions()
    ref.refine_focal_length = False
    ref.refine_extra_params = False
    res = pycolmap.estimate_and_refine_absolute_pose(p2, p3, camera, est, ref)
    n = 0 if res is None else int(res["num_inliers"])
    if n < MIN_QUERY_INLIERS:
        return np.empty(0), np.empty(0), n, f"its pose explains only {n} of {len(p2)} matches (need {MIN_QUERY_INLIERS})"
    pose = res["cam_from_world"]
    return pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64), n, ""


def pose_scene(scene: Scene, image_dir: Path, work_dir: Path, opts: SfmOptions,
               threads: int) -> tuple[Scene, dict[str, str]]:
    """Posed copy of ``scene`` (images under ``image_dir`` by frame name) and {name: why not posed};
    features are extracted and matched on `threads` threads (see reconstruction.colmap_threads)."""
    frames = scene.frames
    mapping = [f for f in frames if f.split == "train"]
    if len(mapping) < MIN_MAPPING_IMAGES:
        raise SfmError(f"scene {scene.name!r}: SfM needs at least {MIN_MAPPING_IMAGES} mapping photos, got "
                       f"{len(mapping)}: COLMAP keeps only points seen in 3 or more photos")
    db_path = work_dir / "database.db"
    extract(frames, image_dir, db_path, opts, threads)
    match(frames, db_path, work_dir, opts, has_poses=False, threads=threads)
    po = pipeline_options(opts)
    po.image_names = [f.name for f in mapping]  # queries never enter the reconstruction
    model_dir = work_dir / "posing"
    model_dir.mkdir()
    models = pycolmap.incremental_mapping(db_path, image_dir, model_dir, options=po)
    if not models:
        raise SfmError(f"scene {scene.name!r}: COLMAP could not initialise a reconstruction from the "
                       f"{len(mapping)} mapping photos (too few matches; do the photos overlap?)")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    db = pycolmap.Database.open(db_path)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        mapped = {by_name[f.name].image_id: by_name[f.name] for f in mapping if f.name in by_name}
        posed: list[Frame] = []
        missing: dict[str, str] = {}
        for f in frames:
            if f.split == "train":
                if f.name not in by_name:
                    missing[f.name] = "not registered by incremental mapping (too few matches to the model)"
                    continue
                im = by_name[f.name]
                pose = im.cam_from_world()
                R, t = pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64)
                cam = rec.cameras[im.camera_id]
            else:
                cam_id = db.read_image_with_name(f.name).camera_id
                if cam_id not in rec.cameras:
                    missing[f.name] = "its camera has no registered mapping photo"
                    continue
                cam = rec.cameras[cam_id]
                R, t, _, why = register_query(db, rec, ids[f.name], mapped, cam, opts.seed)
                if why:
                    missing[f.name] = why
                    continue
            posed.append(replace(f, camera=_camera(cam), R=R, t=t, focal_known=True))
    finally:
        db.close()
    for name, why in missing.items():
        log.warning("%s: not posed: %s", name, why)
    if 2 * len(posed) < len(frames):
        first = next(iter(missing.items()))
        raise SfmError(f"scene {scene.name!r}: SfM posed only {len(posed)} of {len(frames)} photos (need half); "
                       f"first unposed: {first[0]}: {first[1]}")
    log.info("posed %s by SfM: %d of %d photos (%d mapping, %d query), %d points", scene.name, len(posed),
             len(frames), sum(f.split == "train" for f in posed), sum(f.split == "test" for f in posed),
             rec.num_points3D())
    check_registration(db_path, posed, scene.name)  # a symmetric object's look-alike sides (doppelgangers)
    return replace(scene, frames=posed, pose_source="sfm"), missing
