"""Triangulation of the mapping images with their poses held fixed: COLMAP's point triangulator
(`pycolmap.triangulate_points`) step by step, with its bundle adjustment split so that it runs on
several threads and gives the bits of one.

With every pose and camera held fixed, the bundle adjustment of a point depends on that point's
observations only. COLMAP solves all points as one problem, and on several threads its sums of
residuals come in varying order (the model differs from run to run). Here the points, in id order,
are cut into groups of `points_per_problem` (a count that does not depend on the threads), each
group is one problem solved on one thread, and the groups run side by side: the same model for any
thread count. The rest is COLMAP's own, in its order: each image triangulated, tracks completed and
merged, retriangulation, then up to `ba_global_max_refinements` rounds of adjustment, track
completion and filtering until fewer than `ba_global_max_refinement_change` of the observations
change, and each point's colour the mean of its observations' pixels.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from pathlib import Path

import pycolmap

from usvc.core.cores import cores_available

log = logging.getLogger(__name__)


def _fixed_pose_options(po: pycolmap.IncrementalPipelineOptions) -> pycolmap.IncrementalPipelineOptions:
    """What COLMAP's point triangulator sets: existing frames fixed, intrinsics not refined."""
    po.fix_existing_frames = True
    po.ba_refine_focal_length = False
    po.ba_refine_principal_point = False
    po.ba_refine_extra_params = False
    return po


def _adjust_points(rec: pycolmap.Reconstruction, ba: pycolmap.BundleAdjustmentOptions, points_per_problem: int,
                   pool: ThreadPoolExecutor | None) -> None:
    """Bundle adjustment of every point with poses and cameras constant, in groups of points."""
    ids = sorted(rec.points3D.keys())

    def solve(group: list[int]) -> None:
        config = pycolmap.BundleAdjustmentConfig()
        for point_id in group:
            config.add_variable_point(point_id)  # its observations' poses and cameras stay constant
        pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()

    groups = [ids[k:k + points_per_problem] for k in range(0, len(ids), points_per_problem)]
    if pool is None:
        for group in groups:
            solve(group)
    else:
        for _ in pool.map(solve, groups):  # each group's points are its own: no two write the same memory
            pass


def triangulate_posed(rec: pycolmap.Reconstruction, db_path: Path, image_dir: Path,
                      po: pycolmap.IncrementalPipelineOptions, points_per_problem: int,
                      threads: int) -> pycolmap.Reconstruction:
    """Triangulate the matches in `db_path` into `rec` (its images posed, no points yet), refine the
    points with their poses fixed and colour them from the images in `image_dir`, on `threads`
    threads (-1: every core this process may use); returns the model (the same for any `threads`)."""
    po = _fixed_pose_options(po)
    threads = threads if threads > 0 else cores_available()
    db = pycolmap.Database.open(db_path)
    try:
        cache_options = pycolmap.DatabaseCacheOptions()
        cache_options.min_num_matches = po.min_num_matches
        cache_options.ignore_watermarks = po.ignore_watermarks
        cache = pycolmap.DatabaseCache.create(db, cache_options)
    finally:
        db.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    tri = po.get_triangulation()
    for image_id in rec.reg_image_ids():
        mapper.triangulate_image(tri, image_id)
    rec = mapper.reconstruction
    ba = po.get_global_bundle_adjustment()
    ba.ceres.solver_options.num_threads = 1
    mapper_options = po.get_mapper()
    mapper.complete_and_merge_tracks(tri)
    mapper.retriangulate(tri)
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="usvc-ba") if threads > 1 else nullcontext() as pool:
        for _ in range(po.ba_global_max_refinements):
            observations = rec.compute_num_observations()
            mapper.observation_manager.filter_observations_with_negative_depth()
            _adjust_points(rec, ba, points_per_problem, pool)
            changed = mapper.complete_and_merge_tracks(tri) + mapper.filter_points(mapper_options)
            if observations == 0 or changed / observations < po.ba_global_max_refinement_change:
                break
    mapper.clear_modified_points3D()
    rec.extract_colors_for_all_images(str(image_dir), num_threads=1)  # as COLMAP's triangulator ends
    log.debug("triangulated %d points from %d images", rec.num_points3D(), rec.num_reg_images())
    return rec

