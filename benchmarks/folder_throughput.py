"""Photos per second for a folder of photos: a scene's query photos (decoded from their files, or
at --size as arrays) localized with its own map through `Relocalizer.localize_many`, one photo at a
time and several at once (--workers), each worker with the threads divided among them, the worker
counts alternating --rounds times. The photos are the scene's queries repeated --repeat times;
every answer is checked bit for bit against the same photo localized alone with the same threads
per query. Writes
results/benchmarks/folder_throughput_<scene>[_<size>][_<device>].json.
Run (nothing else heavy running):
python benchmarks/folder_throughput.py --scene-dir data/bird --workers 1 2      # a 2-core CPU
python benchmarks/folder_throughput.py --scene-dir data/bird --workers 1 4 8 16 --device cuda
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import usvc  # noqa: E402,F401  (first: it sets OpenMP's wait policy before torch loads)
import numpy as np  # noqa: E402
import torch  # noqa: E402

from _photos import query_photos  # noqa: E402
from _report import scene_of, write_report  # noqa: E402

from usvc.core.scene_file import read_scene_h5  # noqa: E402
from usvc.pipeline.paths import ScenePaths  # noqa: E402
from usvc.relocalize.photo_batch import query_threads, threads_per_query  # noqa: E402
from usvc.relocalize.relocalizer import Relocalizer  # noqa: E402


def _same(a, b) -> bool:
    return (a.rejected == b.rejected and np.array_equal(a.R, b.R, equal_nan=True)
            and np.array_equal(a.t, b.t, equal_nan=True))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene-dir", type=Path, required=True)
    ap.add_argument("--size", help="WxH: the photos cropped to its aspect ratio and resized, as arrays "
                                   "(default: decoded from their files by each query)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3, help="the queries this many times over")
    ap.add_argument("--rounds", type=int, default=3,
                    help="every worker count this many times, alternating (a machine's speed drifts)")
    ap.add_argument("--device", default="cpu", help="the relocalizer's device: auto | cpu | cuda | cuda:N")
    args = ap.parse_args()
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
    alone, runs = {}, {w: [] for w in args.workers}
    for workers in args.workers:
        with query_threads(threads_per_query(threads, workers)):  # each photo alone with those threads
            alone[workers] = [reloc.localize(image, intrinsics) for image, intrinsics in photos]
    for _ in range(args.rounds):
        for workers in args.workers:
            start = time.perf_counter()
            answers = list(reloc.localize_many(batch, workers=workers))
            seconds = time.perf_counter() - start
            same = sum(_same(a, alone[workers][k % len(photos)]) for k, a in enumerate(answers))
            runs[workers].append({"seconds": seconds, "same_answers_as_alone": same,
                                  "answered": sum(a.success for a in answers)})
            print(f"workers {workers:2d} ({threads_per_query(threads, workers)} threads each): "
                  f"{len(batch) / seconds:.2f} photos/s; same answers {same} of {len(batch)}")
    rows = []
    for workers in args.workers:
        rates = [len(batch) / r["seconds"] for r in runs[workers]]
        rows.append({"workers": workers, "threads_per_query": threads_per_query(threads, workers),
                     "photos": len(batch), "photos_per_second_median": float(np.median(rates)),
                     "photos_per_second": rates, "ms_per_photo_median": 1000 / float(np.median(rates)),
                     "same_answers_as_alone": min(r["same_answers_as_alone"] for r in runs[workers]),
                     "answered": runs[workers][0]["answered"]})
        print(f"workers {workers:2d}: median {rows[-1]['photos_per_second_median']:.2f} photos/s")
    first = np.asarray(photos[0][0]) if args.size else None
    name = scene_of(args.scene_dir) + (f"_{first.shape[1]}x{first.shape[0]}" if first is not None else "") \
        + ("" if args.device == "cpu" else f"_{reloc.device}")
    write_report(f"folder_throughput_{name}", {"scene": scene_of(args.scene_dir), "queries": len(photos),
                                               "repeat": args.repeat, "threads": threads,
                                               "device": str(reloc.device), "decoded_by_each_query": not args.size,
                                               "rows": rows})


if __name__ == "__main__":
    main()
