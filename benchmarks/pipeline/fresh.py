"""What a new user's first command costs: the pipeline in a fresh clone, stage by stage.

It clones the committed repository (HEAD) into a temporary directory and runs a plain `dvc repro`
there (every stage of every scene in params.yaml: the bundled scene), timing each stage's whole
process (interpreter start and imports included) and its peak resident memory through a `python`
shim on PATH. It writes `results/benchmarks/pipeline_fresh.json`: per-stage seconds and peak MB,
the total wall time of `dvc repro`, the scene's headline metrics, and whether the clone's
`dvc.lock` came out as committed (and which stages' outputs differ when not).

With `--map PHOTOS` it times a real capture's mapping the same way: `usvc map PHOTOS --name NAME
--format FORMAT` in the fresh clone (the photos copied in, the scene added, its stages run), written
to `results/benchmarks/pipeline_fresh_<NAME>.json`.

    python -m benchmarks.pipeline fresh
    python -m benchmarks.pipeline fresh --map ../shared/scenes/office --format llff --name officemap

Run it on an otherwise idle machine; the numbers are only as clean as the machine is quiet.
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

from benchmarks._report import ROOT, report_name, write_out, write_report
from benchmarks.pipeline._stages import HEADLINE, machine
from usvc.pipeline.paths import ScenePaths

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


def fresh_repro(photos: Path | None = None, fmt: str = "images", name: str = "capture") -> dict:
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
        if photos is not None:  # the clone's own usvc (the working directory comes first for `python -c`)
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
    for row in stages:
        print(f"{row['stage']:>10} {row['scene'] or '':<8} {row['seconds']:8.1f} s  peak {row['peak_memory_mb']:.0f} MB")
    print(f"{what} from a fresh clone: {total:.1f} s; dvc.lock as committed: {not differing}")
    return {
        "mode": f"fresh clone, {what}",
        "timed_command": shlex.join(["usvc", *command[3:]]) if photos is not None else "dvc repro",
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--map", type=Path, metavar="PHOTOS",
                        help="time `usvc map PHOTOS` in the clone instead of `dvc repro` (a real capture's "
                             "mapping, every stage of it)")
    parser.add_argument("--format", default="images", help="with --map: the capture's format (usvc map --format)")
    parser.add_argument("--name", default="capture", help="with --map: the scene name it is added as")
    parser.add_argument("--out", type=Path, help="a copy of the figures here too")


def run(args: argparse.Namespace) -> None:
    result = fresh_repro(args.map, args.format, args.name)
    if args.out:
        write_out(args.out, json.dumps(result, indent=1) + "\n")
    print(f"-> {write_report(report_name(args, None if args.map is None else args.name), result)}")
