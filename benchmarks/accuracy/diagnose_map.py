"""Diagnose a scene's map: fit on training views, generalisation to held-out mapping views and queries,
keypoint 3D error, the encoders' track-retrieval probe, and the accuracy the pipeline measured.

Held-out mapping views exist when the buffer was built with `buffer.holdout_every=k` (every k-th
mapping image withheld from training); the queries are scored too but only as a read-out, never
for choosing settings. The metrics come from the scene's `metrics.json` and `train.json` (and
`baseline.json` when `accuracy baseline-sift` has run). Method notes: benchmarks/accuracy/diagnosis.py.

Run: python -m benchmarks.accuracy diagnose-map --scene bird [--views 16] [override ...]
Writes results/<scene name>/diagnosis.json (or --out), and the same report with the command line
and the machine context to results/benchmarks/accuracy_diagnose_map_<scene name>.json; prints its
fit and track-retrieval parts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch

from benchmarks._report import report_name, write_out, write_report
from benchmarks.accuracy.diagnosis import observations_of, track_retrieval, view_fit_at
from usvc.buffer.buffer_file import read_buffer_attrs, read_buffer_image_names
from usvc.core.images import read_image_bgr
from usvc.core.scene_file import read_scene_h5
from usvc.model.preprocess import luma01
from usvc.pipeline.config import compose_for_script
from usvc.pipeline.logs import script_logging
from usvc.pipeline.stage import scene_paths
from usvc.relocalize.relocalizer import Relocalizer
from usvc.sfm.tracks_file import read_median_depth, read_tracks
from usvc.weights import load_configured_encoder

PROBES = {"small": (0.5, None, "ace"), "default": (1.0, None, "ace"), "xfeat": (1.0, None, "xfeat")}


def _gray(path: Path) -> np.ndarray:
    return luma01(read_image_bgr(path), rgb=False)


def _spread(frames: list, n: int) -> list:
    if len(frames) <= n:
        return frames
    return [frames[i] for i in np.linspace(0, len(frames) - 1, n).round().astype(int)]


def _group(reloc: Relocalizer, frames: list, tracks, median_depth: float) -> dict:
    fits, short = [], []
    for f in frames:
        gray, _ = reloc.working_image(_gray(f.image_path))  # the map's working resolution
        coords = reloc.scene_coordinates(gray)
        uv, xyz = observations_of(tracks, f.name)
        short.append(min(gray.shape))
        fits.append(view_fit_at(coords, gray.shape[::-1], f.camera, f.R, f.t, uv, xyz, median_depth))
    if not fits:
        return {"views": 0}
    kp = [v.keypoint_err_rel for v in fits if np.isfinite(v.keypoint_err_rel)]
    return {"views": len(fits),
            "median_reprojection_px": float(np.median([v.median_px for v in fits])),
            # the same error in pixels of a 480 px short side (ACE's), comparable across working resolutions
            "median_reprojection_px_at_480": float(np.median([v.median_px * 480 / s for v, s in zip(fits, short)])),
            "cells_within_10px": float(np.mean([v.inlier_10px for v in fits])),
            "median_keypoint_err_pct_depth": float(100 * np.median(kp)) if kp else None,
            "keypoint_observations": int(sum(v.keypoints for v in fits))}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True)
    parser.add_argument("--views", type=int, default=16, help="views per group (spread over the split)")
    parser.add_argument("--probe-encoders", nargs="*", choices=sorted([*PROBES, "map"]), default=sorted(PROBES),
                        help="encoders whose track-retrieval probe to run (map: the configured model's)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("overrides", nargs="*")


def run(args: argparse.Namespace) -> None:
    script_logging()
    cfg = compose_for_script(args.scene, args.overrides)
    torch.manual_seed(0)
    paths = scene_paths(cfg)
    scene = read_scene_h5(paths.scene_file)
    tracks = read_tracks(paths.tracks_file)
    median_depth = read_median_depth(paths.tracks_file)
    trained = set(read_buffer_image_names(paths.buffer_file))
    mapping = scene.split("train")
    reloc = Relocalizer(paths.map_file, cfg.model.encoder_weights)
    groups = {"training_views": _spread([f for f in mapping if f.name in trained], args.views),
              "heldout_mapping_views": _spread([f for f in mapping if f.name not in trained], args.views),
              "queries": scene.split("test")}
    report: dict = {"scene": scene.name, "median_depth": median_depth, "working_short_side": reloc.short_side,
                    "buffer": read_buffer_attrs(paths.buffer_file),
                    "fit": {k: _group(reloc, v, tracks, median_depth) for k, v in groups.items()}}
    images = {f.name: _gray(f.image_path) for f in _spread(mapping, 48)}
    heldout = {f.name: _gray(f.image_path) for f in groups["heldout_mapping_views"]}
    probes = dict(PROBES, map=(cfg.model.encoder_width, cfg.model.encoder_weights, cfg.model.encoder))
    report["track_retrieval"], report["track_retrieval_heldout"] = {}, {}
    for name in args.probe_encoders:
        encoder, _ = load_configured_encoder(*probes[name])
        report["track_retrieval"][name] = track_retrieval(encoder, images, tracks)
        if len(heldout) >= 2:  # views no encoder fine-tuned on the scene's mapping images has seen
            report["track_retrieval_heldout"][name] = track_retrieval(encoder, heldout, tracks)
    for name in ("train", "metrics", "baseline"):
        p = Path(cfg.results_dir) / cfg.scene.name / f"{name}.json"
        if p.is_file():
            data = json.loads(p.read_text())
            report[name] = {k: v for k, v in (data.get("mean", data)).items()
                            if isinstance(v, (int, float)) and not k.endswith("_curve")}
    out = args.out or Path(cfg.results_dir) / cfg.scene.name / "diagnosis.json"
    write_out(out, json.dumps(report, indent=2) + "\n")
    print(json.dumps({k: report[k] for k in ("fit", "track_retrieval", "track_retrieval_heldout")}, indent=1))
    write_report(report_name(args, cfg.scene.name), report)

