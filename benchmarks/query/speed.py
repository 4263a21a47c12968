"""Time real queries end to end (photo in, pose out) with each refinement, on a scene's own map.

For a scene folder after its landmarks and train stages (prepared/, map/, landmarks/), every
query photo is localized with refine = none, keypoints, features (the default) and features with
OpenCV's SIFT, at the
photo's own size and, with --size WxH, cropped about the centre to that aspect ratio and resized
to it (square pixels kept, intrinsics moved and scaled with it; a portrait photo gets the size turned). Each figure is the median over the queries after --warmup
untimed ones, split as the relocalizer reports it (preprocess, network, pnp, refine, total);
the map's size on disk (head, landmarks) is recorded beside the SfM model's. Writes
results/benchmarks/query_speed_<scene>[_<W>x<H>][_<device>][_final_<final>].json with the command
line and the machine context. Run (nothing else heavy running, threads as the product uses them):
python -m benchmarks.query speed --scene-dir data/bird --size 640x480   [--device cuda] [--final images]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch

from benchmarks._photos import query_photos
from benchmarks._report import report_name, scene_of, write_report
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize.options import FINAL, REFINE
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer


def _megabytes(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 2**20


VARIANTS = [*REFINE, "features-colmap"]  # the last: refinement by features with COLMAP's SIFT on the query


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True)
    ap.add_argument("--size", help="WxH to resize the queries to (default: as prepared)")
    ap.add_argument("--refine", nargs="+", choices=VARIANTS, default=VARIANTS)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="the relocalizer's device: auto | cpu | cuda | cuda:N")
    ap.add_argument("--final", choices=FINAL, default=RelocalizeOptions.features_final,
                    help="refinement by features' last evidence (relocalize.features_final)")


def run(args: argparse.Namespace) -> None:
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    photos = query_photos(args.scene_dir, size)
    paths = ScenePaths.of_scene_dir(args.scene_dir)
    rows = {}
    for refine in args.refine:
        options = RelocalizeOptions(refine="features", features_extractor="colmap", features_final=args.final) \
            if refine == "features-colmap" else RelocalizeOptions(refine=refine, features_final=args.final)
        reloc = Relocalizer(paths.map_file, options=options, device=args.device)
        for rgb, intr in photos[: args.warmup]:
            reloc.localize(rgb, intr)
        secs = [reloc.localize(rgb, intr).seconds for rgb, intr in photos]
        rows[refine] = {k: float(np.median([s.get(k, 0.0) for s in secs])) for k in secs[0]}
        print(f"{refine:9s} " + "  ".join(f"{k} {1000 * v:.0f} ms" for k, v in rows[refine].items()))
    h, w = photos[0][0].shape[:2]
    sizes = {"map_head_mb": _megabytes(paths.map_file), "landmarks_mb": _megabytes(paths.landmarks),
             "sfm_model_mb": _megabytes(paths.sfm / "model")}
    print({k: round(v, 2) for k, v in sizes.items()})
    name = report_name(args, scene_of(args.scene_dir), f"{w}x{h}" if size else None,
                       None if args.device == "cpu" else reloc.device,
                       None if args.final == RelocalizeOptions.features_final else f"final_{args.final}")
    write_report(name, {"scene": scene_of(args.scene_dir), "queries": len(photos), "image_size": [w, h],
                        "threads": torch.get_num_threads(), "device": str(reloc.device),
                        "features_final": args.final, "seconds_median": rows, **sizes})

