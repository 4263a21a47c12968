"""Two `train` stages side by side against one alone, under a thread setting.

Copies the scene's buffer and SfM tracks into a scratch data folder under two names, times one
`python -m stages.train` run alone, then two started together, and writes
`results/benchmarks/train_side_by_side_<scene>_<threads>.json` with each wall time and the ratio
(side by side over alone). With `threads=auto` each of the two takes half the cores; with the core
count (what every process took before the thread policy) they fight. Run it on an otherwise idle
machine:

    python -m benchmarks.train side-by-side --scene mini --iterations 600 --threads auto
    python -m benchmarks.train side-by-side --scene mini --iterations 600 --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks._report import ROOT, report_name, write_report
from benchmarks.train._stage import copy_scene, train_command


def _run_together(commands: list[list[str]], env: dict[str, str]) -> list[float]:
    start = time.perf_counter()
    procs = [subprocess.Popen(c, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for c in commands]
    ends = [0.0] * len(procs)
    pending = set(range(len(procs)))
    while pending:
        for i in list(pending):
            if procs[i].poll() is not None:
                ends[i] = time.perf_counter() - start
                pending.discard(i)
        time.sleep(0.05)
    for p in procs:
        if p.returncode != 0:
            raise SystemExit(f"train failed: {p.stderr.read().strip().splitlines()[-1:]}")
    return ends


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="mini")
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--threads", default="auto")


def run(args: argparse.Namespace) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    with tempfile.TemporaryDirectory(prefix="usvc-side-by-side-") as tmp:
        data = Path(tmp)
        copy_scene(args.scene, data, ("a", "b"))
        alone = _run_together([train_command(args.scene, "a", data, args.iterations, args.threads)], env)[0]
        pair = _run_together([train_command(args.scene, n, data, args.iterations, args.threads)
                              for n in ("a", "b")], env)
    result = {"scene": args.scene, "iterations": args.iterations, "threads": args.threads,
              "cpus": len(os.sched_getaffinity(0)), "alone_seconds": round(alone, 1),
              "side_by_side_seconds": [round(t, 1) for t in pair],
              "ratio": round(max(pair) / alone, 2)}
    write_report(report_name(args, args.scene, args.threads), result)
    print(json.dumps(result))

