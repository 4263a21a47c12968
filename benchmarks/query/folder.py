"""Photos per second for a folder of photos: a scene's query photos (decoded from their files, or
at --size as arrays) localized with its own map through `Relocalizer.localize_many`, one photo at a
time and several at once (--workers), each worker with the threads divided among them, the worker
counts alternating --rounds times. The photos are the scene's queries repeated --repeat times;
every answer is checked bit for bit against the same photo localized alone with the same threads
per query. With --processes each worker count above one runs as worker processes too (their start
included in the time). Writes
results/benchmarks/query_folder_<scene>[_<size>][_<device>][_processes].json.
Run (nothing else heavy running):
python -m benchmarks.query folder --scene-dir data/bird --workers 1 2      # a 2-core CPU
python -m benchmarks.query folder --scene-dir data/bird --workers 1 4 8 16 --device cuda
python -m benchmarks.query folder --scene-dir data/mini --workers 1 2 --repeat 5 --processes
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import usvc  # noqa: F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np
import torch

from benchmarks._photos import query_photos
from benchmarks._report import report_name, scene_of, write_report
from usvc.core.scene_file import read_scene_h5
from usvc.pipeline.paths import ScenePaths
from usvc.relocalize.photo_batch import query_threads, threads_per_query
from usvc.relocalize.relocalizer import Relocalizer


def _same(a, b) -> bool:
    return (a.rejected == b.rejected and np.array_equal(a.R, b.R, equal_nan=True)
            and np.array_equal(a.t, b.t, equal_nan=True))


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--scene-dir", type=Path, required=True)
    ap.add_argument("--size", help="WxH: the photos cropped to its aspect ratio and resized, as arrays "
                                   "(default: decoded from their files by each query)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3, help="the queries this many times over")
    ap.add_argument("--rounds", type=int, default=3,
                    help="every worker count this many times, alternating (a machine's speed drifts)")
    ap.add_argument("--device", default="cpu", help="the relocalizer's device: auto | cpu | cuda | cuda:N")
    ap.add_argument("--processes", action="store_true",
                    help="also every worker count above one as processes (localize_many(processes=True): "
                         "their start included in the time)")


def run(args: argparse.Namespace) -> None:
    threads = torch.get_num_threads()
    paths = ScenePaths.of_scene_dir(args.scene_dir)
    if args.size:
        size = tuple(int(v) for v in args.size.lower().split("x"))
        photos = query_photos(args.scene_dir, size)
    else:  # paths: each query decodes its photo (EXIF orientation, as `usvc localize` reads it)
        photos = [(f.image_path, (*f.camera.focal, *f.camera.principal_point))
                  for f in read_scene_h5(paths.scene_file).split("test")]
    batch = photos * args.repeat
    reloc = Relocalizer(paths.map_file, device=args.device)
    for image, intrinsics in photos[:2]:  # warm-up
        reloc.localize(image, intrinsics)
    alone = {}
    kinds = [(w, kind) for w in args.workers for kind in ("threads", "processes")
             if kind == "threads" or (args.processes and w > 1)]
    runs: dict[tuple[int, str], list[dict]] = {k: [] for k in kinds}
    for workers in args.workers:
        with query_threads(threads_per_query(threads, workers)):  # each photo alone with those threads
            alone[workers] = [reloc.localize(image, intrinsics) for image, intrinsics in photos]
    for _ in range(args.rounds):
        for workers, kind in kinds:
            start = time.perf_counter()
            answers, first = [], None
            for answer in reloc.localize_many(batch, workers=workers, processes=kind == "processes"):
                answers.append(answer)
                first = first or time.perf_counter() - start
            seconds = time.perf_counter() - start
            same = sum(_same(a, alone[workers][k % len(photos)]) for k, a in enumerate(answers))
            runs[workers, kind].append({"seconds": seconds, "first_answer_seconds": first,
                                        "same_answers_as_alone": same, "answered": sum(a.success for a in answers)})
            print(f"workers {workers:2d} {kind:9s} ({threads_per_query(threads, workers)} threads each): "
                  f"{len(batch) / seconds:.2f} photos/s ({(len(batch) - 1) / (seconds - first):.2f} after the "
                  f"first answer, {first:.2f} s); same answers {same} of {len(batch)}")
    rows = []
    for workers, kind in kinds:
        rates = [len(batch) / r["seconds"] for r in runs[workers, kind]]
        after = [(len(batch) - 1) / (r["seconds"] - r["first_answer_seconds"]) for r in runs[workers, kind]]
        rows.append({"workers": workers, "kind": kind, "threads_per_query": threads_per_query(threads, workers),
                     "photos": len(batch), "photos_per_second_median": float(np.median(rates)),
                     "after_first_answer_photos_per_second_median": float(np.median(after)),
                     "first_answer_seconds_median": float(np.median([r["first_answer_seconds"]
                                                                     for r in runs[workers, kind]])),
                     "photos_per_second": rates, "ms_per_photo_median": 1000 / float(np.median(rates)),
                     "same_answers_as_alone": min(r["same_answers_as_alone"] for r in runs[workers, kind]),
                     "answered": runs[workers, kind][0]["answered"]})
        print(f"workers {workers:2d} {kind:9s}: median {rows[-1]['photos_per_second_median']:.2f} photos/s, "
              f"{rows[-1]['after_first_answer_photos_per_second_median']:.2f} after the first answer")
    first = np.asarray(photos[0][0]) if args.size else None
    shown = f"{first.shape[1]}x{first.shape[0]}" if first is not None else None
    name = report_name(args, scene_of(args.scene_dir), shown, None if args.device == "cpu" else reloc.device,
                       "processes" if args.processes else None)
    write_report(name, {"scene": scene_of(args.scene_dir), "queries": len(photos), "repeat": args.repeat,
                        "threads": threads, "device": str(reloc.device), "decoded_by_each_query": not args.size,
                        "rows": rows})

