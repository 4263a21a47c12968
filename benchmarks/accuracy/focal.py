"""What does not knowing the query's focal length cost? Localize each query of a prepared scene
twice with the same map: with its calibrated focal length, and with ``intrinsics=None`` (focal
estimated with the pose, pycolmap P4Pf + refinement, principal point at the image centre).

Prints (and with ``--out`` writes) JSON: the usual accuracy summary for both, and the relative
focal error of the estimate per query (median and max). Writes the same, with the command line
and the machine context, to results/benchmarks/accuracy_focal_<scene folder name>.json.
Run after the relocalize stage of a scene, e.g.
python -m benchmarks.accuracy focal --scene-dir data/office --out focal_office.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch

from benchmarks._report import report_name, scene_of, write_out, write_report
from usvc.core.pose_errors import rotation_error_deg, summarize, translation_error
from usvc.core.scene_file import read_scene_h5
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize.relocalizer import Relocalizer
from usvc.sfm.tracks_file import read_median_depth


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="data/<scene> with prepared/, sfm/, map/")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--out", type=Path)


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    paths = ScenePaths.of_scene_dir(args.scene_dir)
    scene = read_scene_h5(paths.scene_file)
    depth = read_median_depth(paths.tracks_file)
    reloc = Relocalizer(paths.map_file)
    queries = scene.split("test")
    report: dict = {"scene_dir": str(args.scene_dir), "n_queries": len(queries), "threads": args.threads}
    focal_err = []
    for mode in ("known", "estimated"):
        rot, tr, failed, ms = [], [], [], []
        for f in queries:
            K = f.camera.params if mode == "known" else None
            est = reloc.localize(f.image_path, tuple(K) if K is not None else None)
            failed.append(not est.success)
            rot.append(float(rotation_error_deg(est.R, f.R)) if est.success else np.inf)
            tr.append(float(translation_error(est.R, est.t, f.R, f.t)) if est.success else np.inf)
            ms.append(1e3 * est.seconds["total"])
            if mode == "estimated" and est.camera is not None:
                focal_err.append(abs(est.camera.params[0] / f.camera.params[0] - 1))
        report[mode] = summarize(rot, tr, scene.metric_scale, depth, failed, float(np.mean(ms)))
    report["focal_rel_error_median"] = float(np.median(focal_err)) if focal_err else None
    report["focal_rel_error_max"] = float(np.max(focal_err)) if focal_err else None
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        write_out(args.out, text + "\n")
    write_report(report_name(args, scene_of(args.scene_dir)), report)

