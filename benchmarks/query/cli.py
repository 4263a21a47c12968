"""Time `usvc localize` as a user runs it: one command per photo (each photo the first of its
process, so every one-time cost of a query is in it) and one command for all of them (the first
answer, then the steady ones).

The scene's query photos (`benchmarks._photos.query_photos`: at --size, cropped to its aspect ratio and
resized, intrinsics moved with them) are written as JPEG files to a temporary folder; each command
is `usvc --threads N localize --map <scene>/map/map.pt --intrinsics fx fy cx cy <photos>`, in its own
process, as a shell runs it. The figures are the command line's own answers (`seconds`: from the
decoded photo to the pose, for each photo) and each command's wall time (interpreter start, imports
and the map's load included), --rounds times over. Writes
results/benchmarks/query_cli_<scene>[_<W>x<H>].json.
Run (nothing else heavy running):
python -m benchmarks.query cli --scene-dir data/office --size 1280x720 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks._photos import query_photos
from benchmarks._report import ROOT, report_name, scene_of, write_report
from usvc.pipeline.paths import ScenePaths


def localize_command(map_file: Path, intrinsics: tuple, photos: list[Path], threads: int) -> list[str]:
    """The `usvc localize` command line for `photos`, all with the same (fx, fy, cx, cy)."""
    return [sys.executable, "-m", "usvc.cli", "--threads", str(threads), "localize", "--map", str(map_file),
            "--intrinsics", *(f"{v:.6g}" for v in intrinsics), *map(str, photos)]


def run_command(cmd: list[str]) -> tuple[list[dict], float]:
    """The command's answers (one JSON line each) and its wall seconds; a failed command raises."""
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return [json.loads(line) for line in proc.stdout.splitlines() if line.strip()], wall


def summary(values: list[float]) -> dict:
    return {"median": float(np.median(values)), "max": float(np.max(values)), "min": float(np.min(values)),
            "n": len(values)}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True)
    ap.add_argument("--size", help="WxH to resize the queries to (default: as prepared)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2, help="usvc --threads")
    ap.add_argument("--limit", type=int, default=0, help="the first N query photos only (0: all)")


def run(args: argparse.Namespace) -> None:
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    photos = query_photos(args.scene_dir, size)
    if args.limit > 0:
        photos = photos[: args.limit]
    map_file = ScenePaths.of_scene_dir(args.scene_dir).map_file
    rows: dict[str, list] = {"single": [], "together": []}
    walls: dict[str, list] = {"single": [], "together": []}
    with tempfile.TemporaryDirectory(prefix="usvc-localize-cli-") as tmp:
        files = []
        for k, (rgb, _) in enumerate(photos):
            files.append(Path(tmp) / f"query_{k:03d}.jpg")
            cv2.imwrite(str(files[-1]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
        same = all(np.allclose(intr, photos[0][1]) for _, intr in photos)
        for r in range(args.rounds):
            for path, (_, intr) in zip(files, photos):
                answers, wall = run_command(localize_command(map_file, intr, [path], args.threads))
                rows["single"] += answers
                walls["single"].append(wall)
            if same:  # one command for every photo needs one set of intrinsics
                answers, wall = run_command(localize_command(map_file, photos[0][1], files, args.threads))
                rows["together"] += [{**a, "position": k} for k, a in enumerate(answers)]
                walls["together"].append(wall)
            print(f"round {r + 1}: single " + " ".join(f"{1000 * a['seconds']['total']:.0f}"
                                                      for a in rows["single"][-len(files):]) + " ms")
    total = {kind: [a["seconds"]["total"] for a in answers] for kind, answers in rows.items()}
    result = {
        "scene": scene_of(args.scene_dir), "queries": len(photos), "image_size": list(photos[0][0].shape[1::-1]),
        "threads": args.threads, "rounds": args.rounds,
        "single_photo_seconds": summary(total["single"]),
        "single_photo_command_wall_seconds": summary(walls["single"]),
        "answered": sum(bool(a["success"]) for a in rows["single"]),
    }
    if total["together"]:
        first = [a["seconds"]["total"] for a in rows["together"] if a["position"] == 0]
        rest = [a["seconds"]["total"] for a in rows["together"] if a["position"] > 0]
        result.update({"together_first_seconds": summary(first),
                       "together_after_first_seconds": summary(rest) if rest else None,
                       "together_command_wall_seconds": summary(walls["together"])})
    result["answers"] = {kind: [{"name": Path(a["name"]).name, "success": a["success"], "seconds": a["seconds"]}
                                for a in answers] for kind, answers in rows.items()}
    for key, value in result.items():
        if isinstance(value, dict) and "median" in value:
            print(f"{key}: median {1000 * value['median']:.0f} ms, max {1000 * value['max']:.0f} ms (n={value['n']})")
    w, h = result["image_size"]
    write_report(report_name(args, result["scene"], f"{w}x{h}" if size else None), result)

