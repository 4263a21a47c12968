"""The metrics step: score the relocalized query poses against the scene's ground truth ->
per-query plots and table (plots/), the summary figures, and headline.json."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from usvc.core.atomic import atomic_file
from usvc.core.poses_file import read_poses_txt
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.evaluate import PER_QUERY_COLUMNS, evaluate_initial_poses, evaluate_poses, headline_figures
from usvc.metrics.plots import write_plots
from usvc.relocalize.queries_file import read_query_stats, read_refinement_records
from usvc.sfm.tracks_file import read_median_depth

log = logging.getLogger("usvc")


@dataclass(frozen=True)
class Inputs:
    scene: Path  # the prepared scene (prepared/scene.h5): ground-truth poses, metric scale
    tracks: Path  # the SfM model (sfm/tracks.h5): its median depth scales relative errors
    poses: Path  # the estimated poses (relocalize/poses.txt)
    queries: Path  # the per-query records (relocalize/queries.h5)


def run(inputs: Inputs, out: Path, *, headline: Path) -> dict:
    """Write the plots into `out` and the headline figures to `headline`; returns every figure."""
    scene = read_scene_h5(inputs.scene)
    median_depth = read_median_depth(inputs.tracks)
    estimates = read_poses_txt(inputs.poses)
    stats = read_query_stats(inputs.queries)
    summary, rows = evaluate_poses(scene, estimates, stats, median_depth)
    records = read_refinement_records(inputs.queries)
    if records is not None:  # older queries.h5 files have no pre-refinement poses
        summary = {**summary, **evaluate_initial_poses(scene, records, stats, median_depth)}
    write_plots(out, rows, PER_QUERY_COLUMNS, scene.metric_scale, median_depth, f"{scene.name}: relocalization")
    with atomic_file(headline) as tmp:
        figures = headline_figures(summary, metric=scene.metric_scale is not None)
        tmp.write_text(json.dumps(figures, indent=2, sort_keys=True) + "\n")
    key = "acc_5cm_5deg" if scene.metric_scale is not None else "acc_rel_5cm_5deg"
    log.info("metrics %s: %s=%.3f over %d queries (%d failed), median %.3g deg%s",
             scene.name, key, summary[key], summary["n_queries"], summary["n_failed"], summary["median_rot_deg"],
             " (against SfM pseudo ground truth)" if scene.pose_source == "sfm" else "")
    if f"initial_{key}" in summary and summary[f"initial_{key}"] is None:
        log.info("metrics %s: before refinement: not computed (no answered query has a learned pose, "
                 "as with relocalize.prior=none)", scene.name)
    elif f"initial_{key}" in summary:
        log.info("metrics %s: before refinement %s=%.3f; refined pose kept for %.0f%% of queries",
                 scene.name, key, summary[f"initial_{key}"], 100 * summary["refine_kept_fraction"])
    # "sfm": the queries' poses were estimated by SfM here (pseudo ground truth), not given
    return {**summary, "ground_truth": scene.pose_source}
