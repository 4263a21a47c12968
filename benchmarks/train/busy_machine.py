"""A `train` stage on a machine that does other things: alone, beside a busy loop, beside a second stage.

Copies the scene's buffer and SfM tracks into a scratch data folder and runs `python -m
stages.train` (`threads=auto`) in three conditions: alone; while a busy loop (a Python process
that never sleeps, not a usvc job, so `auto` still gives the stage every core) runs; and started
together with a second `train` stage (`auto` then gives each one core). Each condition runs under
the OpenMP wait policies of POLICIES: threads that sleep at once at a barrier
(`OMP_WAIT_POLICY=PASSIVE`), threads that spin 1,000 rounds first (`GOMP_SPINCOUNT=1000`), and the
runtime's own default (300,000 rounds); the runtime's default comes from an empty
`OMP_WAIT_POLICY`, which the runtime ignores with a warning and usvc leaves alone.
Throughput is the training loop's own: iterations / `train_seconds` from each run's train.json
and train.timing.json, so interpreter start and file reading do not count.

    python -m benchmarks.train busy-machine --scene mini --iterations 200 --repeats 2

Writes results/benchmarks/train_busy_machine_<scene>.json. Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks._report import ROOT, report_name, write_report
from benchmarks.train._stage import copy_scene, train_command
from usvc.pipeline.metrics_file import read_metrics

# label -> the OpenMP variables of that run ("" = unset for the runtime, which then uses its default)
POLICIES = {"passive": {"OMP_WAIT_POLICY": "PASSIVE"},
            "spin 1000, then sleep": {"OMP_WAIT_POLICY": "", "GOMP_SPINCOUNT": "1000"},
            "runtime default (spin 300000, then sleep)": {"OMP_WAIT_POLICY": ""}}
BUSY_LOOP = [sys.executable, "-c", "while True: pass"]


def _iterations_per_second(data: Path, name: str) -> float:
    stats = read_metrics(data / "results" / name / "train.json")  # figures and timings
    return stats["iterations"] / stats["train_seconds"]


def _run(names: list[str], scene: str, data: Path, iterations: int, threads: str, env: dict[str, str],
         busy: bool) -> list[float]:
    loop = subprocess.Popen(BUSY_LOOP) if busy else None
    try:
        if loop is not None:
            time.sleep(1.0)
        procs = [subprocess.Popen(train_command(scene, n, data, iterations, threads), cwd=ROOT, env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for n in names]
        for p in procs:
            _, err = p.communicate()
            if p.returncode != 0:
                raise SystemExit(f"train failed: {err.strip().splitlines()[-1:]}")
    finally:
        if loop is not None:
            loop.kill()
            loop.wait()
    return [round(_iterations_per_second(data, n), 2) for n in names]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="mini")
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--threads", default="auto")
    parser.add_argument("--repeats", type=int, default=3, help="alone runs per policy")


def run(args: argparse.Namespace) -> None:
    base = {k: v for k, v in os.environ.items()
            if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_WAIT_POLICY",
                         "GOMP_SPINCOUNT", "USVC_EXPORTED_THREADS")}
    result: dict = {"scene": args.scene, "iterations": args.iterations, "threads": args.threads,
                    "cpus": len(os.sched_getaffinity(0)), "policies": {}}
    with tempfile.TemporaryDirectory(prefix="usvc-busy-") as tmp:
        data = Path(tmp)
        copy_scene(args.scene, data, ("a", "b"))
        # Alone: the policies alternate, `--repeats` times, so a drift of the machine hits both alike.
        alone: dict[str, list[float]] = {label: [] for label in POLICIES}
        for _ in range(args.repeats):
            for label, policy in POLICIES.items():
                alone[label] += _run(["a"], args.scene, data, args.iterations, args.threads,
                                     {**base, **policy}, busy=False)
        for label, policy in POLICIES.items():
            env = {**base, **policy}
            busy = _run(["a"], args.scene, data, args.iterations, args.threads, env, busy=True)[0]
            pair = _run(["a", "b"], args.scene, data, args.iterations, args.threads, env, busy=False)
            mean = float(np.mean(alone[label]))
            row = {"alone_it_per_s": alone[label], "alone_mean": round(mean, 2),
                   "alone_std": round(float(np.std(alone[label])), 2),
                   "beside_busy_loop_it_per_s": busy, "beside_busy_loop_kept": round(busy / mean, 3),
                   "beside_second_stage_it_per_s": pair, "beside_second_stage_kept": round(min(pair) / mean, 3)}
            result["policies"][label] = row
            print(label, json.dumps(row), flush=True)
    write_report(report_name(args, args.scene), result)

