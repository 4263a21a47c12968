"""Wall time and peak memory of each pipeline stage, as `dvc repro` runs them.

Two modes. `--fresh` measures what a new user's first command costs: it clones the committed
repository (HEAD) into a temporary directory and runs a plain `dvc repro` there (every stage of
every scene in params.yaml: the bundled scene), timing each stage's whole process (interpreter
start and imports included) and its peak resident memory through a `python` shim on PATH. It
writes `results/benchmarks/fresh_repro.json`: per-stage seconds and peak MB, the total wall time
of `dvc repro`, the scene's headline metrics, and whether the clone's `dvc.lock` came out as
committed (and which stages' outputs differ when not).

    python benchmarks/pipeline_time.py --fresh
    python benchmarks/pipeline_time.py --fresh --map ../shared/scenes/office --format llff --name officemap

With `--map PHOTOS` it times a real capture's mapping the same way: `usvc map PHOTOS --name NAME
--format FORMAT` in the fresh clone (the photos copied in, the scene added, its stages run), written
to `results/benchmarks/fresh_map_<NAME>.json`.

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
import shlex
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

HEADLINE = ("median_trans_cm", "median_trans_rel_cm", "median_rot_deg", "n_queries")
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


def machine(results: Path, scenes: list[str]) -> dict:
    """What the seconds depend on besides the code: the CPU, whether it runs bf16 natively, and the
    precision each scene's training ran at (`train.precision: auto` follows the CPU)."""
    from usvc.core.device import device_name
    from usvc.core.precision import cpu_has_native_bf16

    precision = {}
    for scene in scenes:
        path = ScenePaths(results.parent / "data", results, scene).metrics("train")
        if path.exists():
            precision[scene] = json.loads(path.read_text()).get("precision")
    return {"cpu_model": device_name("cpu"), "native_bf16": cpu_has_native_bf16(), "train_precision": precision}


def _lock_outs(lock: dict) -> dict[str, list[str]]:
    """stage -> the md5 of each of its outputs, from a parsed dvc.lock."""
    return {name: [o.get("md5", "") for o in stage.get("outs", [])] for name, stage in lock.get("stages", {}).items()}


def fresh_repro(out: Path, photos: Path | None = None, fmt: str = "images", name: str = "capture") -> None:
    """Clone HEAD, `dvc repro` in the clone (or, given `photos`, `usvc map photos --name name
    --format fmt`, which adds the scene and runs its stages), and record what each stage process cost."""
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
        command = [sys.executable, "-m", "dvc", "repro"]
        if photos is not None:  # the clone's own usvc (the working directory comes first on sys.path)
            command = [sys.executable, "-c", "from usvc.cli import main; raise SystemExit(main())", "map",
                       str(photos.resolve()), "--name", name, "--format", fmt]
        t0 = time.perf_counter()
        proc = subprocess.run(command, cwd=clone, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True)
        total = time.perf_counter() - t0
        what = "dvc repro" if photos is None else "usvc map"
        if proc.returncode != 0:
            raise SystemExit(f"{what} failed in the clone (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
        stages = []
        for line in timing.read_text().splitlines():
            row = json.loads(line)
            argv = row["argv"]
            stage = argv[1].removeprefix("stages.") if argv[:1] == ["-m"] and len(argv) > 1 else " ".join(argv)
            scene = next((a.split("=", 1)[1] for a in argv if a.startswith("scene=")), None)
            stages.append({"stage": stage, "scene": scene, "seconds": round(row["seconds"], 2),
                           "peak_memory_mb": round(row["peak_memory_mb"], 1)})
        committed = _lock_outs(yaml.safe_load((ROOT / "dvc.lock").read_text()) if (ROOT / "dvc.lock").exists() else {})
        produced = _lock_outs(yaml.safe_load((clone / "dvc.lock").read_text()))
        differing = sorted(k for k in produced if committed.get(k) != produced[k])
        # the scenes that ran (a mapped capture only: the others' tracked results are the committed ones)
        scenes = [name] if photos is not None else yaml.safe_load((clone / "params.yaml").read_text())["scenes"]
        metrics = {}
        for scene in scenes:
            path = ScenePaths(clone / "data", clone / "results", scene).metrics("metrics")
            if path.exists():
                values = json.loads(path.read_text())
                metrics[scene] = {k: v for k, v in values.items() if k.startswith("acc_") or k in HEADLINE}
        machine_info = machine(clone / "results", list(scenes))
    result = {
        "mode": f"fresh clone, {what}",
        "command": shlex.join(["usvc", *command[3:]]) if photos is not None else "dvc repro",
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
        **machine_info,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    for row in stages:
        print(f"{row['stage']:>10} {row['scene'] or '':<8} {row['seconds']:8.1f} s  peak {row['peak_memory_mb']:.0f} MB")
    print(f"{what} from a fresh clone: {total:.1f} s; dvc.lock as committed: {not differing} -> {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fresh", action="store_true",
                        help="clone HEAD into a temporary directory and time a plain `dvc repro` there")
    parser.add_argument("--map", type=Path, metavar="PHOTOS",
                        help="with --fresh: time `usvc map PHOTOS` in the clone instead of `dvc repro` (a real "
                             "capture's mapping, every stage of it)")
    parser.add_argument("--format", default="images", help="with --map: the capture's format (usvc map --format)")
    parser.add_argument("--name", default="capture", help="with --map: the scene name it is added as")
    parser.add_argument("--scene")
    parser.add_argument("--stages", nargs="+", default=[*MAPPING, *QUERYING])
    parser.add_argument("--threads", type=int, default=0,
                        help="set OMP_NUM_THREADS/MKL_NUM_THREADS for every stage (0: leave the environment)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides passed to every stage (after --)")
    args = parser.parse_args()
    if args.map is not None and not args.fresh:
        parser.error("--map times a fresh clone's `usvc map`: give --fresh too")
    if args.fresh:
        default = "fresh_repro.json" if args.map is None else f"fresh_map_{args.name}.json"
        fresh_repro(args.out or ROOT / "results" / "benchmarks" / default, args.map, args.format, args.name)
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
    copy = write_report(f"pipeline_time_{name}", result)
    print(f"mapping ({' + '.join(result['mapping_stages'])}): {mapping:.1f} s -> {out}, {copy}")


if __name__ == "__main__":
    main()
