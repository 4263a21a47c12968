"""Sparse reconstruction of the mapping images with pycolmap.

Known poses are held fixed and only points are triangulated (COLMAP's point_triangulator);
without poses a full incremental reconstruction runs instead. A dense posed capture is
reconstructed from its keyframes only (usvc/sfm/keyframes.py).
"""

from __future__ import annotations

import logging
import os
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.errors import SfmError
from usvc.core.scene import Frame
from usvc.sfm.keyframes import mapping_keyframes
from usvc.sfm.opencv_extraction import write_opencv_features
from usvc.sfm.options import SfmOptions
from usvc.sfm.pair_matching import colmap_matching, exhaustive_pairs, image_names, match_pairs
from usvc.sfm.point_triangulation import triangulate_posed
from usvc.sfm.pose_check import pose_agreement, warn_if_poses_disagree
from usvc.sfm.retrieval_pairs import retrieval_pairs

log = logging.getLogger(__name__)

# Pose-guided pairs only between cameras whose viewing directions differ by less than this.
_PAIR_MAX_ANGLE_DEG = 60.0


MIN_MAPPING_IMAGES = 3  # COLMAP's triangulator ignores two-view tracks


def colmap_threads(opts: SfmOptions, threads: int) -> int:
    """Feature extraction, matching and posed triangulation threads: sfm.num_threads when set (> 0),
    else `threads`, the caller's thread count (-1, COLMAP's default: all cores). Matching splits its
    pairs among them (pair_matching), triangulation its points (point_triangulation), each with the
    bits of one thread."""
    return opts.num_threads if opts.num_threads > 0 else threads


def _camera_key(frame: Frame) -> tuple:
    c = frame.camera
    return (c.model, c.width, c.height, tuple(round(v, 6) for v in c.params))


def register_images(frames: list[Frame], db_path: Path) -> dict[tuple, int]:
    """Cameras, rigs, frames and images in name order, so image ids (which orient every pair in
    geometric verification) do not depend on which extraction thread finishes first."""
    camera_ids: dict[tuple, int] = {}
    # A camera's focal length is a prior (verify with essential matrices, refine in BA) unless
    # some photo of it had to guess one (no EXIF): then COLMAP estimates it.
    known: dict[tuple, bool] = defaultdict(lambda: True)
    for f in frames:
        known[_camera_key(f)] &= f.focal_known
    db = pycolmap.Database.open(db_path)
    try:
        for k, f in enumerate(sorted(frames, key=lambda f: f.name), start=1):
            key = _camera_key(f)
            if key not in camera_ids:
                cid = len(camera_ids) + 1
                c = f.camera
                cam = pycolmap.Camera(model=c.model, width=c.width, height=c.height, params=list(c.params),
                                      camera_id=cid)
                cam.has_prior_focal_length = known[key]
                db.write_camera(cam, use_camera_id=True)
                rig = pycolmap.Rig()
                rig.rig_id = cid
                rig.add_ref_sensor(cam.sensor_id)
                db.write_rig(rig, use_rig_id=True)
                camera_ids[key] = cid
            image = pycolmap.Image(name=f.name, camera_id=camera_ids[key], image_id=k)
            db.write_image(image, use_image_id=True)
            frame = pycolmap.Frame()
            frame.frame_id, frame.rig_id = k, camera_ids[key]
            frame.add_data_id(image.data_id)
            db.write_frame(frame, use_frame_id=True)
    finally:
        db.close()
    return camera_ids


def extract(frames: list[Frame], image_dir: Path, db_path: Path, opts: SfmOptions, threads: int) -> None:
    """SIFT into a fresh database whose cameras are the scene's exact intrinsics, on `threads`
    threads unless sfm.num_threads is set (see colmap_threads): COLMAP's, or OpenCV's
    (sfm.extractor=opencv, `opencv_extraction`)."""
    camera_ids = register_images(frames, db_path)
    if opts.extractor == "opencv":
        count = colmap_threads(opts, threads)
        write_opencv_features(db_path, image_dir, sorted(f.name for f in frames), opts.max_num_features,
                              count if count > 0 else (os.cpu_count() or 1))
        return
    groups: dict[int, list[str]] = defaultdict(list)
    for f in frames:
        groups[camera_ids[_camera_key(f)]].append(f.name)
    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = opts.max_num_features
    eo.num_threads = colmap_threads(opts, threads)
    eo.use_gpu = False
    for cid, names in groups.items():
        ro = pycolmap.ImageReaderOptions()
        ro.existing_camera_id = cid
        pycolmap.extract_features(
            db_path, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=ro, extraction_options=eo, device=pycolmap.Device.cpu,
        )


def pose_pairs(frames: list[Frame], k: int) -> list[tuple[str, str]]:
    """Each image with its k nearest cameras (by centre) that look roughly the same way."""
    centers = np.stack([f.center for f in frames])
    dirs = np.stack([f.R[2] for f in frames])  # optical axis in world coordinates
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    cos = np.clip(dirs @ dirs.T, -1, 1)
    dist[np.degrees(np.arccos(cos)) > _PAIR_MAX_ANGLE_DEG] = np.inf
    np.fill_diagonal(dist, np.inf)
    pairs: set[tuple[str, str]] = set()
    for i in range(len(frames)):
        for j in np.argsort(dist[i])[:k]:
            if np.isfinite(dist[i, j]):
                a, b = sorted((frames[i].name, frames[j].name))
                pairs.add((a, b))
    return sorted(pairs)


def matching_kwargs(opts: SfmOptions) -> dict:
    """Matcher and seeded geometric-verification options for pycolmap's match_* calls (CPU, one
    matcher thread; see pair_matching.colmap_matching)."""
    return colmap_matching(opts.seed)


def match(frames: list[Frame], db_path: Path, work_dir: Path, opts: SfmOptions, has_poses: bool,
          threads: int = 1, capture_images: int | None = None) -> str:
    """Match with the configured strategy; `auto` is exhaustive for small scenes (up to
    sfm.exhaustive_max_images of `capture_images`, the capture's mapping frames, default
    len(frames): keyframes of a dense capture are matched pose-guided), else pose-guided
    (with poses) or by retrieval (without: any file order). Exhaustive, pose-guided and retrieved
    pairs are matched on `threads` threads (see colmap_threads) with the bits of one
    (pair_matching); sequential matching runs on one."""
    mode = opts.matching
    if mode == "auto":
        if (len(frames) if capture_images is None else capture_images) <= opts.exhaustive_max_images:
            mode = "exhaustive"
        else:
            mode = "poses" if has_poses else "retrieval"
    if mode == "poses" and not has_poses:
        raise SfmError("sfm.matching=poses needs a scene with poses")
    common = matching_kwargs(opts)
    count = colmap_threads(opts, threads)
    count = count if count > 0 else (os.cpu_count() or 1)
    if mode == "exhaustive":
        match_pairs(db_path, exhaustive_pairs(image_names(db_path)), work_dir, opts.seed, count)
    elif mode == "retrieval":
        pairs = retrieval_pairs(db_path, opts.retrieval_neighbors, opts.sequential_overlap, opts.retrieval_words,
                                opts.seed)
        match_pairs(db_path, pairs, work_dir, opts.seed, count)
    elif mode == "sequential":
        po = pycolmap.SequentialPairingOptions()
        po.overlap = opts.sequential_overlap
        pycolmap.match_sequential(db_path, pairing_options=po, **common)
    else:
        match_pairs(db_path, pose_pairs(frames, opts.pose_pairs_per_image), work_dir, opts.seed, count)
    return mode


def pipeline_options(opts: SfmOptions) -> pycolmap.IncrementalPipelineOptions:
    """Mapper and triangulator options with every RANSAC seeded, so reruns give the same model."""
    po = pycolmap.IncrementalPipelineOptions()
    po.random_seed = opts.seed
    po.mapper.random_seed = opts.seed
    po.triangulation.random_seed = opts.seed
    # COLMAP's threaded bundle adjustment sums residuals in varying order; the resulting float noise
    # flips point filtering at thresholds. Triangulation with poses runs its own on several threads
    # (point_triangulation: the same bits for any count).
    po.num_threads = 1
    po.mapper.num_threads = 1
    return po


def posed_reconstruction(frames: list[Frame], db_path: Path) -> pycolmap.Reconstruction:
    """An empty model whose image ids are the database's and whose poses are the given ones
    (only the database images among ``frames`` enter it)."""
    by_name = {f.name: f for f in frames}
    db = pycolmap.Database.open(db_path)
    try:
        rec = pycolmap.Reconstruction()
        for cam in db.read_all_cameras():
            rec.add_camera_with_trivial_rig(cam)
        for im in db.read_all_images():
            if im.name not in by_name:  # e.g. queries whose features share the database
                continue
            f = by_name[im.name]
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(f.R), f.t)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id), pose
            )
    finally:
        db.close()
    return rec


def align_to_poses(rec: pycolmap.Reconstruction, frames: list[Frame], seed: int) -> None:
    """Bring a free reconstruction into the scene's frame (similarity on camera centres)."""
    centers = np.stack([f.center for f in frames])
    spread = float(np.median(np.linalg.norm(centers - centers.mean(0), axis=1)))
    ro = pycolmap.RANSACOptions()
    ro.max_error = 0.05 * max(spread, 1e-9)
    ro.random_seed = seed
    sim = pycolmap.align_reconstruction_to_locations(rec, [f.name for f in frames], centers, 3, ro)
    if sim is None:
        raise SfmError("could not align the incremental reconstruction to the given camera centres")
    rec.transform(sim)


def reconstruct(frames: list[Frame], image_dir: Path, work_dir: Path, opts: SfmOptions,
                has_poses: bool, threads: int) -> tuple[pycolmap.Reconstruction, dict]:
    """Extract (on `threads` threads, see colmap_threads), match and triangulate (or map) the
    mapping frames, or only their keyframes when the capture is posed and dense (mapping_keyframes);
    returns the model and timing/strategy stats."""
    capture_images = len(frames)
    frames = mapping_keyframes(frames, opts, has_poses)
    if len(frames) < MIN_MAPPING_IMAGES:
        raise SfmError(
            f"SfM needs at least {MIN_MAPPING_IMAGES} mapping images, got {len(frames)}"
            + (f" keyframes of {capture_images} (lower sfm.keyframe_min_translation or sfm.keyframe_min_rotation_deg)"
               if len(frames) < capture_images else "")
            + ": COLMAP keeps only points seen in 3 or more images (tracks of two views are dropped), and a usable "
            "map wants dozens")
    db_path = work_dir / "database.db"
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    extract(frames, image_dir, db_path, opts, threads)
    timings["extract_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    strategy = match(frames, db_path, work_dir, opts, has_poses, threads, capture_images)
    timings["match_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mode = opts.reconstruction
    if mode == "auto":
        mode = "triangulate" if has_poses else "incremental"
    if mode == "triangulate" and not has_poses:
        raise SfmError("sfm.reconstruction=triangulate needs a scene with poses")
    agreement = {}
    if has_poses:
        agreement = pose_agreement(db_path, frames)
        warn_if_poses_disagree(agreement)
    model_dir = work_dir / "colmap_work"
    model_dir.mkdir(exist_ok=True)
    po = pipeline_options(opts)
    if mode == "triangulate" and opts.points_per_problem > 0:
        rec = triangulate_posed(posed_reconstruction(frames, db_path), db_path, image_dir, po,
                                opts.points_per_problem, colmap_threads(opts, threads))
    elif mode == "triangulate":
        rec = pycolmap.triangulate_points(
            posed_reconstruction(frames, db_path), db_path, image_dir, model_dir, options=po,
            refine_intrinsics=False,
        )
    else:
        models = pycolmap.incremental_mapping(db_path, image_dir, model_dir, options=po)
        if not models:
            raise SfmError("incremental mapping registered no images: too few matches")
        rec = max(models.values(), key=lambda r: r.num_reg_images())
        if has_poses:
            align_to_poses(rec, frames, opts.seed)
    timings["reconstruct_s"] = time.perf_counter() - t0
    if rec.num_points3D() < opts.min_points:
        raise SfmError(
            f"SfM triangulated only {rec.num_points3D()} points from {len(frames)} images "
            f"(sfm.min_points={opts.min_points}): too few matches, a degenerate scene or wrong poses"
        )
    return rec, {"matching": strategy, "reconstruction": mode, "mapping_frames": capture_images, **timings,
                 **{f"pose_check_{k}": v for k, v in agreement.items() if k != "worst_images"}}
