"""Wall time and peak memory of each pipeline stage, as `dvc repro` runs them.

Two modes. `--fresh` measures what a new user's first command costs: it clones the committed
repository (HEAD) into a temporary directory and runs a plain `dvc repro` there (every stage of
every scene in params.yaml: the bundled scene), timing each stage's whole process (interpreter
start and imports included) and its peak resident memory through a `python` shim on PATH. It
writes `results/benchmarks/fresh_repro.json`: per-stage seconds and peak MB, the total wall time
of `dvc repro`, the scene's headline metrics, and whether the clone's `dvc.lock` came out as
committed (and which stages' outputs differ when not).

    python benchmarks/pipeline_time.py --fresh

Without `--fresh`, it runs `python -m stages.<stage> scene=<scene> [overrides]` for the mapping
and query stages in this checkout, each in its own process, and writes
`results/<scene>/pipeline_time.json` (or `--out`): seconds and peak resident memory per stage, the
mapping total (every stage before `relocalize`), and the time per query; a copy, with the command
line and the machine context, goes to `results/benchmarks/pipeline_time_<scene>.json` (<scene>: the
`scene.name` override when given). Stages rewrite their usual artifacts; `dvc status` then shows
whether they still match the lock.

    python benchmarks/pipeline_time.py --scene office
    python benchmarks/pipeline_time.py --scene mini --threads 1 -- train.iterations=3000

Run either on an otherwise idle machine; the numbers are only as clean as the machine is quiet.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from _report import write_report

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from usvc.pipeline.metrics_file import read_metrics  # noqa: E402
from usvc.pipeline.paths import ScenePaths  # noqa: E402

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


def read_json(path: Path) -> dict:
    """A stage's JSON record, or {} when there is none (the stage did not write it)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def timing_record(results: Path, stage: str) -> dict:
    """What the stage recorded about itself (`<stage>.timing.json` in the scene's results folder:
    seconds, peak memory, device), or {} when it wrote none."""
    return read_json(results / ("prepared.timing.json" if stage == "prepare" else f"{stage}.timing.json"))


def stage_peak_mb(results: Path, stage: str) -> float | None:
    """The peak resident memory the stage itself recorded in its metrics JSON."""
    value = timing_record(results, stage).get("peak_memory_mb")
    return round(value, 1) if isinstance(value, (int, float)) else None


SHIM = """#!{python}
import json, os, subprocess, sys, time
t0 = time.perf_counter()
child = subprocess.Popen([{python!r}, *sys.argv[1:]])
_, status, usage = os.wait4(child.pid, 0)
code = os.waitstatus_to_exitcode(status)
with open(os.environ["USVC_TIMING_LOG"], "a") as fh:
    fh.write(json.dumps({{"argv": sys.argv[1:], "seconds": time.perf_counter() - t0,
                          "peak_memory_mb": usage.ru_maxrss / 1024.0, "exit": code}}) + "\\n")
sys.exit(code)
"""


def _lock_outs(lock: dict) -> dict[str, list[str]]:
    """stage -> the md5 of each of its outputs, from a parsed dvc.lock."""
    return {name: [o.get("md5", "") for o in stage.get("outs", [])] for name, stage in lock.get("stages", {}).items()}


def fresh_repro(out: Path) -> None:
    """Clone HEAD, `dvc repro` in the clone, and record what each stage process cost."""
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="usvc-fresh-") as tmp:
        clone = Path(tmp) / "usvc"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        shim_dir = Path(tmp) / "bin"
        shim_dir.mkdir()
        (shim_dir / "python").write_text(SHIM.format(python=sys.executable))
        (shim_dir / "python").chmod(0o755)
        timing = Path(tmp) / "timing.jsonl"
        env = {**os.environ, "PATH": f"{shim_dir}{os.pathsep}{os.environ.get('PATH', '')}",
               "USVC_TIMING_LOG": str(timing)}
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "dvc", "repro"], cwd=clone, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        total = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"dvc repro failed in the clone (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
        stages = []
        for line in timing.read_text().splitlines():
            row = json.loads(line)
            argv = row["argv"]
            name = argv[1].removeprefix("stages.") if argv[:1] == ["-m"] and len(argv) > 1 else " ".join(argv)
            scene = next((a.split("=", 1)[1] for a in argv if a.startswith("scene=")), None)
            stages.append({"stage": name, "scene": scene, "seconds": round(row["seconds"], 2),
                           "peak_memory_mb": round(row["peak_memory_mb"], 1)})
        committed = _lock_outs(yaml.safe_load((ROOT / "dvc.lock").read_text()) if (ROOT / "dvc.lock").exists() else {})
        produced = _lock_outs(yaml.safe_load((clone / "dvc.lock").read_text()))
        differing = sorted(k for k in produced if committed.get(k) != produced[k])
        scenes = yaml.safe_load((clone / "params.yaml").read_text())["scenes"]
        metrics = {}
        for scene in scenes:
            path = ScenePaths(clone / "data", clone / "results", scene).metrics("metrics")
            if path.exists():
                values = json.loads(path.read_text())
                metrics[scene] = {k: v for k, v in values.items()
                                  if k.startswith("acc_") or k in ("median_trans_cm", "median_rot_deg", "n_queries")}
    result = {
        "mode": "fresh clone, dvc repro",
        "commit": commit,
        "total_seconds": round(total, 1),
        "stage_seconds_sum": round(sum(s["seconds"] for s in stages), 1),
        "stages": stages,
        "peak_memory_mb": max((s["peak_memory_mb"] for s in stages), default=None),
        "dvc_lock_as_committed": not differing,
        "dvc_lock_stages_differing": differing,
        "metrics": metrics,
        "cpus": len(os.sched_getaffinity(0)),
        "threads_env": os.environ.get("OMP_NUM_THREADS", "unset"),
        "cpu": platform.processor() or platform.machine(),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    for row in stages:
        print(f"{row['stage']:>10} {row['scene'] or '':<8} {row['seconds']:8.1f} s  peak {row['peak_memory_mb']:.0f} MB")
    print(f"dvc repro from a fresh clone: {total:.1f} s; dvc.lock as committed: {not differing} -> {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fresh", action="store_true",
                        help="clone HEAD into a temporary directory and time a plain `dvc repro` there")
    parser.add_argument("--scene")
    parser.add_argument("--stages", nargs="+", default=[*MAPPING, *QUERYING])
    parser.add_argument("--threads", type=int, default=0,
                        help="set OMP_NUM_THREADS/MKL_NUM_THREADS for every stage (0: leave the environment)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides passed to every stage (after --)")
    args = parser.parse_args()
    if args.fresh:
        fresh_repro(args.out or ROOT / "results" / "benchmarks" / "fresh_repro.json")
        return
    if not args.scene:
        parser.error("--scene is required (or --fresh)")
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
    reloc = ScenePaths(ROOT / "data", ROOT / "results", name).metrics("relocalize")
    if "relocalize" in args.stages and reloc.exists():
        stats = read_metrics(reloc)  # figures and the stage's own per-query timing (model loading excluded)
        result["ms_per_query"] = round(stats["ms_per_query"], 1)
        result["queries"] = stats["queries"]
    out = args.out or ROOT / "results" / name / "pipeline_time.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    copy = write_report(f"pipeline_time_{name}", result)
    print(f"mapping ({' + '.join(result['mapping_stages'])}): {mapping:.1f} s -> {out}, {copy}")


if __name__ == "__main__":
    main()
