"""How well do `success` and `confidence` (inlier fraction of the cells) separate right answers from wrong ones?

For every ``--scene-dir`` (a scene after its relocalize stage: prepared/, sfm/, map/, landmarks/)
this localizes, with that scene's map, the default refinement (``--refine`` to change it) and
``--min-confidence`` (default 0: no confidence threshold, so the table can sweep it):
- each query as it is (known intrinsics), and turned sideways (90°, intrinsics turned with it,
  ground truth turned with it), and with its focal length given 2x too large and 2x too small;
- pure noise images of the query size;
- every photo under each ``--foreign`` folder (photos of other places), with the query focal
  length scaled to the photo's width.
An answer is right when it is within 5° and 3 % of the median scene depth of the truth
(foreign photos and noise have no right answer). For each threshold the report gives the
precision of the answers it accepts and the recall of right answers it keeps, and picks the
smallest threshold at which precision >= --precision.

Prints the report without its per-threshold table and per-answer rows; writes all of it to
results/benchmarks/accuracy_confidence_<scene>[+<scene> ...][_final_<final>].json (the --scene-dir
folder names, in order), with the command line and the machine context, and to --out when given.

Run: python -m benchmarks.accuracy confidence --scene-dir data/office --scene-dir data/mini \
        --foreign ../shared/scenes/bird --out confidence.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import cv2
import numpy as np
import torch

from benchmarks._report import report_name, scene_of, write_out, write_report
from usvc.core.images import read_image_bgr
from usvc.core.pose_errors import rotation_error_deg, translation_error
from usvc.core.scene import Camera
from usvc.core.scene_file import read_scene_h5
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize.options import FINAL, REFINE
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer
from usvc.sfm.tracks_file import read_median_depth

ROT_DEG, TRANS_FRAC = 5.0, 0.03
TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera axes after turning the image clockwise


def _pinhole(cam: Camera) -> tuple[float, float, float, float]:
    (fx, fy), (cx, cy) = cam.focal, cam.principal_point
    return fx, fy, cx, cy


def _foreign_photos(folders: list[Path], limit: int) -> list[Path]:
    photos: list[Path] = []
    for folder in folders:
        found = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        step = max(1, len(found) // limit)
        photos += found[::step][:limit]
    return photos


def _answer(est, kind: str, scene: str, R_gt=None, t_gt=None, depth: float = 1.0) -> dict:
    right = False
    if est.success and R_gt is not None:
        rot = float(rotation_error_deg(est.R, R_gt))
        tr = float(translation_error(est.R, est.t, R_gt, t_gt))
        right = rot < ROT_DEG and tr < TRANS_FRAC * depth
    return {"scene": scene, "kind": kind, "success": bool(est.success), "confidence": est.confidence,
            "right": right, "rejected": est.rejected, "path": est.refine_path,
            "feature_inliers": int(est.feature_inliers)}


def run_scene(scene_dir: Path, foreign: list[Path], noise: int, seed: int, options: RelocalizeOptions) -> list[dict]:
    paths = ScenePaths.of_scene_dir(scene_dir)
    scene = read_scene_h5(paths.scene_file)
    depth = read_median_depth(paths.tracks_file)
    reloc = Relocalizer(paths.map_file, options=options)
    name = scene.name
    rows = []
    queries = scene.split("test")
    for f in queries:
        fx, fy, cx, cy = _pinhole(f.camera)
        bgr = read_image_bgr(f.image_path)
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        h, w = rgb.shape[:2]
        rows.append(_answer(reloc.localize(rgb, (fx, fy, cx, cy)), "query", name, f.R, f.t, depth))
        # turned 90° clockwise: pixel (u, v) -> (h - v, u) in the new image (continuous coordinates)
        turned = np.ascontiguousarray(np.rot90(rgb, -1))
        rows.append(_answer(reloc.localize(turned, (fy, fx, h - cy, cx)), "sideways", name,
                            TURN @ f.R, TURN @ f.t, depth))
        for factor in (2.0, 0.5):
            rows.append(_answer(reloc.localize(rgb, (fx * factor, fy * factor, cx, cy)), f"focal x{factor:g}",
                                name, f.R, f.t, depth))
    rng = np.random.default_rng(seed)
    f0 = queries[0]
    fx, fy, cx, cy = _pinhole(f0.camera)
    for _ in range(noise):
        img = rng.integers(0, 256, (f0.camera.height, f0.camera.width, 3), dtype=np.uint8)
        rows.append(_answer(reloc.localize(img, (fx, fy, cx, cy)), "noise", name))
    for path in foreign:
        rgb = cv2.cvtColor(read_image_bgr(path), cv2.COLOR_BGR2RGB)
        h, w = rgb.shape[:2]
        s = w / f0.camera.width
        rows.append(_answer(reloc.localize(rgb, (fx * s, fy * s, w / 2, h / 2)), "foreign", name))
    return rows


def thresholds_report(rows: list[dict], precision: float) -> dict:
    conf = np.array([r["confidence"] for r in rows])
    right = np.array([r["right"] for r in rows])
    success = np.array([r["success"] for r in rows])
    n_right = int(right.sum())
    table = []
    for thr in np.round(np.arange(0.0, 0.61, 0.01), 2):
        accepted = success & (conf >= thr)
        n_acc = int(accepted.sum())
        table.append({"threshold": float(thr), "accepted": n_acc, "wrong_accepted": int((accepted & ~right).sum()),
                      "precision": float((accepted & right).sum() / n_acc) if n_acc else 1.0,
                      "recall": float((accepted & right).sum() / n_right) if n_right else 0.0})
    chosen = next((t for t in table if t["precision"] >= precision), None)
    n_acc = int(success.sum())
    as_run = {"accepted": n_acc, "wrong_accepted": int((success & ~right).sum()),
              "precision": float((success & right).sum() / n_acc) if n_acc else 1.0,
              "recall": float((success & right).sum() / n_right) if n_right else 0.0}
    return {"n_answers": len(rows), "n_right": n_right, "as_run": as_run, "chosen": chosen, "table": table}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, action="append", required=True)
    parser.add_argument("--foreign", type=Path, action="append", default=[], help="folders of photos of other places")
    parser.add_argument("--foreign-per-folder", type=int, default=40)
    parser.add_argument("--noise", type=int, default=10, help="noise images per scene")
    parser.add_argument("--precision", type=float, default=0.99)
    parser.add_argument("--focal-tolerance", type=float, default=0.25,
                        help="relocalize.focal_tolerance during the run (0: no focal check)")
    parser.add_argument("--refine", choices=REFINE, default=RelocalizeOptions().refine)
    parser.add_argument("--min-confidence", type=float, default=0.0,
                        help="relocalize.min_confidence during the run (0: sweep it in the table; "
                             f"{RelocalizeOptions().min_confidence:g}: the default, as_run then gives its figures)")
    parser.add_argument("--final", choices=FINAL, default=RelocalizeOptions().features_final,
                        help="relocalize.features_final during the run")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--out", type=Path)


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    rows = []
    for scene_dir in args.scene_dir:
        own = scene_dir.resolve()
        foreign = _foreign_photos([f for f in args.foreign if own.name not in str(f.resolve())], args.foreign_per_folder)
        options = RelocalizeOptions(min_confidence=args.min_confidence, focal_tolerance=args.focal_tolerance,
                                    refine=args.refine, features_final=args.final)
        rows += run_scene(scene_dir, foreign, args.noise, seed=0, options=options)
    kinds = sorted({r["kind"] for r in rows})
    by_kind = {}
    for k in kinds:
        sel = [r for r in rows if r["kind"] == k]
        c = np.array([r["confidence"] for r in sel])
        by_kind[k] = {"n": len(sel), "success": sum(r["success"] for r in sel), "right": sum(r["right"] for r in sel),
                      "rejected_focal": sum("imply a focal length" in r["rejected"] for r in sel),
                      "paths": {p: sum(r["path"] == p for r in sel) for p in sorted({r["path"] for r in sel})},
                      "confidence_min": float(c.min()), "confidence_median": float(np.median(c)),
                      "confidence_max": float(c.max()),
                      "confidence_max_of_wrong": float(max((r["confidence"] for r in sel if not r["right"]), default=0.0)),
                      "confidence_min_of_right": float(min((r["confidence"] for r in sel if r["right"]), default=1.0))}
    report = {"scenes": [str(s) for s in args.scene_dir], "foreign": [str(f) for f in args.foreign],
              "focal_tolerance": args.focal_tolerance, "refine": args.refine, "min_confidence": args.min_confidence,
              "features_final": args.final,
              "by_kind": by_kind, **thresholds_report(rows, args.precision), "answers": rows}
    text = json.dumps(report, indent=1)
    print(json.dumps({k: v for k, v in report.items() if k not in ("table", "answers")}, indent=1))
    if args.out:
        write_out(args.out, text + "\n")
    final = None if args.final == RelocalizeOptions().features_final else f"final_{args.final}"
    write_report(report_name(args, "+".join(scene_of(s) for s in args.scene_dir), final), report)

