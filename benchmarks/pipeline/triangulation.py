"""Triangulation with poses held fixed, three ways, on one prepared scene's matches: COLMAP's point
triangulator as one problem on one thread (`sfm.points_per_problem=0`), and usvc's, the points'
bundle adjustment in groups (`sfm.points_per_problem`), on one thread and on `--threads`.

SIFT extraction and matching run once (the sfm stage's options, the scene's keyframes); then each
way is timed once a round, the ways alternated over `--rounds` rounds. The report holds each way's
seconds per round and median, its points, and whether the groups gave one model for both thread
counts (a digest of every point's position and track), in
`results/benchmarks/pipeline_triangulation_<scene folder>[_<variant>].json`.

    python -m benchmarks.pipeline triangulation --scene-dir data/room960 --threads 2
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import tempfile
import time
from pathlib import Path

import pycolmap

from benchmarks._report import report_name, write_report
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.pipeline.paths import ScenePaths
from usvc.sfm.keyframes import mapping_keyframes
from usvc.sfm.options import SfmOptions
from usvc.sfm.point_triangulation import triangulate_posed
from usvc.sfm.reconstruction import extract, match, pipeline_options, posed_reconstruction


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="the scene's data folder (data/<scene>)")
    parser.add_argument("--threads", type=int, default=2, help="threads of the threaded way, and of matching")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--points-per-problem", type=int, default=SfmOptions.points_per_problem)


def model_digest(rec: pycolmap.Reconstruction) -> str:
    """Every point's position bits and track, in id order."""
    h = hashlib.sha1()
    for point_id in sorted(rec.points3D):
        point = rec.points3D[point_id]
        h.update(point.xyz.tobytes())
        h.update(repr(sorted((e.image_id, e.point2D_idx) for e in point.track.elements)).encode())
    return h.hexdigest()


def run(args: argparse.Namespace) -> None:
    paths = ScenePaths.of_scene_dir(args.scene_dir)
    scene = read_scene_h5(paths.scene_file)
    opts = SfmOptions()
    frames = mapping_keyframes(scene.split("train"), opts, scene.has_poses)
    images = paths.prepared / IMAGE_DIR
    ways = {"colmap_one_problem_1_thread": None, "groups_1_thread": 1, f"groups_{args.threads}_threads": args.threads}
    seconds: dict[str, list[float]] = {w: [] for w in ways}
    digests: dict[str, set[str]] = {w: set() for w in ways}
    points: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="usvc-triangulation-") as work:
        db = Path(work) / "database.db"
        extract(frames, images, db, opts, args.threads)
        match(frames, db, Path(work), opts, scene.has_poses, args.threads, len(scene.split("train")))
        for round_ in range(args.rounds):
            for way, threads in ways.items():
                start = time.perf_counter()
                if threads is None:
                    out = Path(work) / f"colmap{round_}"
                    out.mkdir()
                    rec = pycolmap.triangulate_points(posed_reconstruction(frames, db), db, images, out,
                                                      options=pipeline_options(opts), refine_intrinsics=False)
                else:
                    rec = triangulate_posed(posed_reconstruction(frames, db), db, images, pipeline_options(opts),
                                            args.points_per_problem, threads)
                seconds[way].append(round(time.perf_counter() - start, 3))
                digests[way].add(model_digest(rec))
                points[way] = rec.num_points3D()
                print(f"round {round_}: {way} {seconds[way][-1]:.2f} s, {points[way]} points", flush=True)
    groups = [w for w, t in ways.items() if t is not None]
    result = {
        "scene_dir": str(args.scene_dir),
        "mapping_frames": len(scene.split("train")),
        "images": len(frames),
        "threads": args.threads,
        "points_per_problem": args.points_per_problem,
        "ways": {w: {"seconds": seconds[w], "median_s": statistics.median(seconds[w]), "points": points[w],
                     "same_model_every_round": len(digests[w]) == 1} for w in ways},
        "groups_same_model_for_any_thread_count": len(set().union(*(digests[w] for w in groups))) == 1,
    }
    path = write_report(report_name(args, args.scene_dir.name), result)
    print(f"-> {path}")
