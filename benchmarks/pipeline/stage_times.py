"""Wall time and peak memory of each pipeline stage of a scene in this checkout, as `dvc repro` runs them.

It runs `python -m stages.<stage> scene=<scene> [overrides]` for the mapping and query stages in
this checkout, each in its own process, and writes `results/<scene>/pipeline_time.json` (or
`--out`): seconds and peak resident memory per stage, the mapping total (every stage before
`relocalize`), and the time per query; a copy, with the command line and the machine context, goes
to `results/benchmarks/pipeline_time_<scene>.json` (<scene>: the `scene.name` override when given).
Stages rewrite their usual artifacts; `dvc status` then shows whether they still match the lock.
What a new user's first command costs, in a fresh clone: `python -m benchmarks.pipeline fresh`.

    python -m benchmarks.pipeline time --scene office
    python -m benchmarks.pipeline time --scene mini --threads 1 -- train.iterations=3000

Run it on an otherwise idle machine; the numbers are only as clean as the machine is quiet.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

from benchmarks._report import ROOT, report_name, write_report
from benchmarks.pipeline._stages import machine, run_stage, stage_peak_mb
from usvc.pipeline.metrics_file import read_metrics
from usvc.pipeline.paths import ScenePaths

MAPPING = ("prepare", "sfm", "keypoints", "buffer", "train")
QUERYING = ("relocalize", "metrics")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True)
    parser.add_argument("--stages", nargs="+", default=[*MAPPING, *QUERYING])
    parser.add_argument("--threads", type=int, default=0,
                        help="set OMP_NUM_THREADS/MKL_NUM_THREADS for every stage (0: leave the environment)")
    parser.add_argument("--out", type=Path, default=None, help="default: results/<scene>/pipeline_time.json")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides passed to every stage (after --)")


def run(args: argparse.Namespace) -> None:
    env = dict(os.environ)
    if args.threads > 0:
        env.update(OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    name = next((o.split("=", 1)[1] for o in args.overrides if o.startswith("scene.name=")), args.scene)
    rows = []
    for stage in args.stages:
        row = run_stage(stage, args.scene, args.overrides, env)
        row["peak_memory_mb"] = stage_peak_mb(ROOT / "results" / name, stage)
        rows.append(row)
        print(f"{stage:>10}: {row['seconds']:8.1f} s, peak {row['peak_memory_mb']} MB", flush=True)
    mapping = sum(r["seconds"] for r in rows if r["stage"] in MAPPING)
    result = {
        "scene": args.scene,
        "overrides": args.overrides,
        "stages": rows,
        "mapping_seconds": round(mapping, 1),
        "mapping_stages": [r["stage"] for r in rows if r["stage"] in MAPPING],
        "cpus": len(os.sched_getaffinity(0)),
        "threads_env": env.get("OMP_NUM_THREADS", "unset"),
        "cpu": platform.processor() or platform.machine(),
        **machine(ROOT / "results", [name]),
    }
    reloc = ScenePaths(ROOT / "data", ROOT / "results", name).metrics("relocalize")
    if "relocalize" in args.stages and reloc.exists():
        stats = read_metrics(reloc)  # figures and the stage's own per-query timing (model loading excluded)
        result["ms_per_query"] = round(stats["ms_per_query"], 1)
        result["queries"] = stats["queries"]
    out = args.out or ROOT / "results" / name / "pipeline_time.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    copy = write_report(report_name(args, name), result)
    print(f"mapping ({' + '.join(result['mapping_stages'])}): {mapping:.1f} s -> {out}, {copy}")
