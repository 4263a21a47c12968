"""Stage: score the relocalized query poses against ground truth; write metrics.json, headline.json and plots."""

import logging
import time

import hydra
from omegaconf import DictConfig

from usvc.core.atomic import atomic_dir
from usvc.core.pose_errors import read_poses_txt
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.evaluate import (
    HEADLINE_FILE,
    PER_QUERY_COLUMNS,
    evaluate_initial_poses,
    evaluate_poses,
    headline_figures,
)
from usvc.metrics.plots import write_plots
from usvc.pipeline.config import register_configs
from usvc.pipeline.metrics_file import write_json
from usvc.pipeline.stage import peak_memory_mb, scene_paths, stage_main, stage_outputs
from usvc.relocalize.queries_file import read_query_stats, read_refinement_records
from usvc.sfm.median_depth import median_scene_depth
from usvc.sfm.tracks import read_tracks

log = logging.getLogger("usvc")
register_configs()


@hydra.main(version_base=None, config_path="../conf", config_name="config")
@stage_main
def main(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    paths = scene_paths(cfg)
    scene = read_scene_h5(paths.prepared)
    median_depth = median_scene_depth(read_tracks(paths.sfm / "tracks.h5"))
    estimates = read_poses_txt(paths.relocalize / "poses.txt")
    stats = read_query_stats(paths.relocalize / "queries.h5")
    summary, rows = evaluate_poses(scene, estimates, stats, median_depth)
    records = read_refinement_records(paths.relocalize / "queries.h5")
    if records is not None:  # older queries.h5 files have no pre-refinement poses
        summary = {**summary, **evaluate_initial_poses(scene, records, stats, median_depth)}

    plots_dir, metrics_path = stage_outputs(cfg, "metrics", artifact="plots")
    with atomic_dir(plots_dir) as tmp:
        write_plots(tmp, rows, PER_QUERY_COLUMNS, scene.metric_scale, median_depth, f"{scene.name}: relocalization")
    # "sfm": the queries' poses were estimated by SfM here (pseudo ground truth), not given
    write_json(metrics_path, {**summary, "ground_truth": scene.pose_source,
                              "seconds": time.perf_counter() - t0, "peak_memory_mb": peak_memory_mb()})
    write_json(metrics_path.with_name(HEADLINE_FILE), headline_figures(summary, metric=scene.metric_scale is not None))
    headline = "acc_5cm_5deg" if scene.metric_scale is not None else "acc_rel_5cm_5deg"
    log.info("metrics %s: %s=%.3f over %d queries (%d failed), median %.3g deg%s",
             scene.name, headline, summary[headline], summary["n_queries"], summary["n_failed"],
             summary["median_rot_deg"],
             " (against SfM pseudo ground truth)" if scene.pose_source == "sfm" else "")
    if f"initial_{headline}" in summary:
        log.info("metrics %s: before refinement %s=%.3f; refined pose kept for %.0f%% of queries",
                 scene.name, headline, summary[f"initial_{headline}"], 100 * summary["refine_kept_fraction"])


if __name__ == "__main__":
    main()
