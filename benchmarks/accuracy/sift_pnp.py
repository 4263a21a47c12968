"""The classical baseline users would pick instead of a learned map: SIFT + PnP against an SfM model.

The mapping images are reconstructed exactly as the sfm stage does it (pycolmap SIFT, the same
matching strategy, points triangulated with the given poses held fixed). Each query's SIFT
features are then matched to every mapping image (exhaustive retrieval, so no pose or retrieval
prior helps it), geometrically verified, lifted to 2D-3D correspondences through the mapping
keypoints' triangulated points, and passed to pycolmap's LO-RANSAC absolute pose with non-linear
refinement (the hloc recipe with SIFT). Nothing of a query enters the model.

The time per query is SIFT extraction (the scene's mean per image) plus matching against every
mapping image plus pose estimation; no GPU is used.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.errors import SfmError
from usvc.core.scene import Frame, Scene
from usvc.sfm.pair_matching import match_listed_pairs
from usvc.sfm.posing import register_query
from usvc.sfm.reconstruction import (
    SfmOptions,
    extract,
    pipeline_options,
    pose_pairs,
    posed_reconstruction,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BaselinePose:
    """One query's result for one RANSAC seed; `R`, `t` are world-to-camera."""

    R: np.ndarray | None  # world-to-camera, None when not localized
    t: np.ndarray | None
    inliers: int
    seconds: float
    why: str  # empty when localized


def _mapping_pairs(mapping: list[Frame], opts: SfmOptions) -> list[tuple[str, str]]:
    """The sfm stage's pairs: exhaustive for small scenes, else pose-guided (the mapping poses are known)."""
    if len(mapping) <= opts.exhaustive_max_images or opts.matching == "exhaustive":
        names = sorted(f.name for f in mapping)
        return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    return pose_pairs(mapping, opts.pose_pairs_per_image)


def _shares_keypoints(db: pycolmap.Database, ids: dict[str, int], model: pycolmap.Reconstruction) -> str:
    """Why the model's images do not carry this database's keypoints, index for index ("" when they do)."""
    for image in model.images.values():
        if image.name not in ids:
            return f"its image {image.name!r} is not in the scene"
        keypoints = db.read_keypoints(ids[image.name])[:, :2]
        xy = np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)
        if keypoints.shape != xy.shape or not np.allclose(keypoints, xy, atol=1e-3):
            return f"its image {image.name!r} has {len(xy)} keypoints, SIFT found {len(keypoints)} or others there"
    return ""


def sift_pnp_baseline(scene: Scene, image_dir: Path, work_dir: Path, opts: SfmOptions, seeds: list[int],
                      threads: int, model: pycolmap.Reconstruction | None = None
                      ) -> tuple[dict[int, dict[str, BaselinePose]], dict[str, float]]:
    """Localize every query of ``scene`` once per RANSAC seed; returns ({seed: {name: pose}}, timings).

    ``image_dir`` holds the prepared (pinhole) images by frame name; ``work_dir`` an empty folder
    for the COLMAP database and model; SIFT runs on ``threads`` threads (see
    :func:`usvc.sfm.reconstruction.colmap_threads`). With ``model`` (the sfm stage's own
    reconstruction) the queries are registered against its points instead of a model triangulated
    here: the mapping photos' SIFT is the stage's (the same extraction), so the matches lift to the
    points usvc's landmarks hold; a model whose keypoints are not those is refused.
    """
    if not scene.has_poses:
        raise SfmError(f"scene {scene.name!r}: the SIFT baseline needs posed mapping images")
    mapping, queries = scene.split("train"), scene.split("test")
    if len(mapping) < 2 or not queries:
        raise SfmError(f"scene {scene.name!r}: the SIFT baseline needs >= 2 mapping images and a query, "
                       f"got {len(mapping)} and {len(queries)}")
    db_path = work_dir / "database.db"
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    extract(scene.frames, image_dir, db_path, opts, threads)
    timings["extract_s_per_image"] = (time.perf_counter() - t0) / len(scene.frames)

    t0 = time.perf_counter()
    if model is None:
        match_listed_pairs(db_path, _mapping_pairs(mapping, opts), work_dir / "mapping_pairs.txt", opts.seed)
        model_dir = work_dir / "model"
        model_dir.mkdir()
        rec = pycolmap.triangulate_points(posed_reconstruction(mapping, db_path), db_path, image_dir, model_dir,
                                          options=pipeline_options(opts), refine_intrinsics=False)
    else:
        rec = model
        with pycolmap.Database.open(db_path) as db:
            why = _shares_keypoints(db, {im.name: im.image_id for im in db.read_all_images()}, rec)
        if why:
            raise SfmError(f"scene {scene.name!r}: the given SfM model cannot be the baseline's: {why}")
    timings["map_s"] = time.perf_counter() - t0
    if rec.num_points3D() < opts.min_points:
        raise SfmError(f"scene {scene.name!r}: the SIFT model has only {rec.num_points3D()} points")
    timings["model_points"] = float(rec.num_points3D())

    query_pairs = [(q.name, m.name) for q in queries for m in mapping]
    t0 = time.perf_counter()
    match_listed_pairs(db_path, query_pairs, work_dir / "query_pairs.txt", opts.seed)
    match_s = (time.perf_counter() - t0) / len(queries)
    timings["match_s_per_query"] = match_s

    results: dict[int, dict[str, BaselinePose]] = {}
    db = pycolmap.Database.open(db_path)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        # by the database's image ids (a given model's own may differ); a given model's images in their
        # order, so that RANSAC's draws do not depend on how the model was read
        posed = [(ids[im.name], im) for im in rec.images.values() if im.has_pose]
        mapped = dict(sorted(posed) if model is not None else posed)
        for seed in seeds:
            results[seed] = {}
            for q in queries:
                c = q.camera
                camera = pycolmap.Camera(model=c.model, width=c.width, height=c.height, params=list(c.params))
                t0 = time.perf_counter()
                R, t, inliers, why = register_query(db, rec, ids[q.name], mapped, camera, seed)
                seconds = time.perf_counter() - t0 + timings["extract_s_per_image"] + match_s
                results[seed][q.name] = BaselinePose(R if not why else None, t if not why else None,
                                                     inliers, seconds, why)
    finally:
        db.close()
    return results, timings
