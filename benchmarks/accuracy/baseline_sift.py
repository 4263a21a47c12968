"""SIFT + PnP against an SfM model: the classical baseline, on the same split as the pipeline.

Needs the scene's prepare and sfm stages (it reads the prepared pinhole images, the split and the
median scene depth from them, and uses the same `sfm` options), then localizes every query once per
RANSAC seed (`benchmarks/accuracy/sift_pnp.py` says how) and scores the poses exactly as the
metrics stage does. Writes results/<scene>/baseline.json (or `--out`; `diagnose-map` reads it
there): per-seed summaries, their mean and standard deviation, timings, and the queries it could
not localize with the reason; the same report, with the command line and the machine context,
also goes to results/benchmarks/accuracy_baseline_sift_<scene name>.json.

With `--model stage` the queries are registered against the sfm stage's own model
(data/<scene>/sfm/model: the points usvc's landmarks hold) instead of one triangulated here, and
the reports are named baseline_stage_model.json and accuracy_baseline_sift_<scene name>_stage_model.json.
With `--poses-dir DIR` each seed's poses go to DIR/poses_seed<N>.txt too, for `compare-poses`.
Run: python -m benchmarks.accuracy baseline-sift --scene office [--seeds 0 1 2] [--model own|stage]
    [--poses-dir DIR] [override ...]
(overrides are Hydra's, e.g. scene.name=office_opencv scene.path=data/raw/office_opencv)
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from benchmarks._report import report_name, write_report
from benchmarks.accuracy.sift_pnp import sift_pnp_baseline
from usvc.core.poses_file import write_poses_txt
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.metrics.evaluate import evaluate_poses
from usvc.pipeline.config import compose_for_script
from usvc.pipeline.logs import script_logging
from usvc.pipeline.stage import scene_paths
from usvc.relocalize.queries_file import QueryStats
from usvc.sfm.reconstruction import SfmOptions
from usvc.sfm.tracks_file import read_median_depth


def mean_std(summaries: list[dict]) -> tuple[dict, dict]:
    """Mean and population std of every numeric figure that all seeds report."""
    keys = [k for k, v in summaries[0].items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and all(s.get(k) is not None for s in summaries)]
    mean = {k: float(np.mean([s[k] for s in summaries])) for k in keys}
    std = {k: float(np.std([s[k] for s in summaries])) for k in keys}
    return mean, std


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="scene config name (conf/scene/<name>.yaml)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="RANSAC seeds")
    parser.add_argument("--out", type=Path, help="default: results/<scene name>/baseline[_stage_model].json")
    parser.add_argument("--model", choices=("own", "stage"), default="own",
                        help="own: triangulate the mapping photos here, as the sfm stage does | stage: the sfm "
                             "stage's model itself")
    parser.add_argument("--poses-dir", type=Path,
                        help="also write each seed's poses there (poses_seed<N>.txt, as the relocalize stage "
                             "writes them: compare-poses reads them)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. scene.name=... data_dir=...")


def run(args: argparse.Namespace) -> None:
    script_logging()
    cfg = compose_for_script(args.scene, args.overrides)
    paths = scene_paths(cfg)
    scene = read_scene_h5(paths.scene_file)
    median_depth = read_median_depth(paths.tracks_file)
    opts = SfmOptions(**cfg.sfm)
    model = None
    if args.model == "stage":
        model_dir = paths.sfm / "model"
        if not (model_dir / "points3D.bin").is_file():
            raise SystemExit(f"--model stage: no SfM model at {model_dir} (run the sfm stage first)")
        model = pycolmap.Reconstruction(str(model_dir))
    suffix = "_stage_model" if model is not None else ""
    with tempfile.TemporaryDirectory(prefix="usvc-baseline-") as work:
        # threads=-1: COLMAP's SIFT on all cores, unless sfm.num_threads says otherwise
        results, timings = sift_pnp_baseline(scene, paths.prepared / IMAGE_DIR, Path(work), opts, args.seeds,
                                             threads=-1, model=model)
    per_seed, failures = {}, {}
    for seed, poses in results.items():
        estimates = {n: (p.R, p.t) for n, p in poses.items() if p.R is not None}
        stats = {n: QueryStats(p.inliers, p.seconds, p.R is not None) for n, p in poses.items()}
        summary, _ = evaluate_poses(scene, estimates, stats, median_depth)
        per_seed[str(seed)] = summary
        failures[str(seed)] = {n: p.why for n, p in poses.items() if p.why}
        if args.poses_dir is not None:
            names = sorted(estimates)
            write_poses_txt(args.poses_dir / f"poses_seed{seed}.txt", names,
                            np.array([estimates[n][0] for n in names]).reshape(-1, 3, 3),
                            np.array([estimates[n][1] for n in names]).reshape(-1, 3))
    mean, std = mean_std(list(per_seed.values()))
    report = {"method": "sift_pnp", "scene": scene.name, "seeds": args.seeds, "model": args.model,
              "sift_max_features": opts.max_num_features, "mean": mean, "std": std, "per_seed": per_seed,
              "not_localized": failures, "timings": timings}
    out = args.out or Path(cfg.results_dir) / scene.name / f"baseline{suffix}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    keys = [k for k in ("acc_5cm_5deg", "acc_2cm_2deg", "acc_1cm_1deg", "acc_rel_5cm_5deg", "acc_rel_2cm_2deg",
                        "acc_rel_1cm_1deg", "median_rot_deg", "median_trans_rel_cm", "ms_per_query") if k in mean]
    print(f"{scene.name}: SIFT + PnP over seeds {args.seeds} ({mean['n_queries']:.0f} queries) -> {out}")
    for k in keys:
        print(f"  {k:22s} {mean[k]:.4g} ± {std[k]:.2g}")
    print(f"-> {write_report(report_name(args, scene.name, suffix.lstrip('_')), report)}")

