"""Wall time and peak memory of each pipeline stage on one scene, as `dvc repro` would run them.

Runs `python -m stages.<stage> scene=<scene> [overrides]` for each stage in order, each in its
own process, and writes `results/<scene>/pipeline_time.json`: seconds and peak resident memory
(as the stage records it) per stage, the mapping total (every stage before `relocalize`), and the time per query. Run it
on an otherwise idle machine; the numbers are only as clean as the machine is quiet.

    python benchmarks/pipeline_time.py --scene office
    python benchmarks/pipeline_time.py --scene mini --threads 1 -- train.iterations=3000

Stages rewrite their usual artifacts (the same ones `dvc repro` writes); `dvc status` then shows
whether they still match the lock.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAPPING = ("prepare", "sfm", "keypoints", "buffer", "train")
QUERYING = ("relocalize", "metrics")


def run_stage(stage: str, scene: str, overrides: list[str], env: dict[str, str]) -> dict:
    """One stage in a child process: its wall seconds and peak RSS (from the child's own rusage)."""
    cmd = [sys.executable, "-m", f"stages.{stage}", f"scene={scene}", *overrides]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate()
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = err.strip().splitlines()[-1] if err.strip() else "(no output)"
        raise SystemExit(f"stage {stage} failed (exit {proc.returncode}): {tail}")
    return {"stage": stage, "seconds": round(seconds, 2)}


def stage_peak_mb(results: Path, stage: str) -> float | None:
    """The peak resident memory the stage itself recorded in its metrics JSON."""
    path = results / ("prepared.json" if stage == "prepare" else f"{stage}.json")
    try:
        value = json.loads(path.read_text()).get("peak_memory_mb")
    except (OSError, ValueError):
        return None
    return round(value, 1) if isinstance(value, (int, float)) else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True)
    parser.add_argument("--stages", nargs="+", default=[*MAPPING, *QUERYING])
    parser.add_argument("--threads", type=int, default=0,
                        help="set OMP_NUM_THREADS/MKL_NUM_THREADS for every stage (0: leave the environment)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides passed to every stage (after --)")
    args = parser.parse_args()
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
    }
    reloc = ROOT / "results" / name / "relocalize.json"
    if "relocalize" in args.stages and reloc.exists():
        stats = json.loads(reloc.read_text())  # the stage's own per-query timing, model loading excluded
        result["ms_per_query"] = round(stats["ms_per_query"], 1)
        result["queries"] = stats["queries"]
    out = args.out or ROOT / "results" / name / "pipeline_time.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"mapping ({' + '.join(result['mapping_stages'])}): {mapping:.1f} s -> {out}")


if __name__ == "__main__":
    main()
