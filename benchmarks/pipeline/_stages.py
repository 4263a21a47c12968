"""A pipeline stage run as `dvc repro` runs it, a process of its own, and what it recorded about
itself: the helpers the pipeline family's subcommands share."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from benchmarks._report import ROOT
from usvc.pipeline.paths import ScenePaths

HEADLINE = ("median_trans_cm", "median_trans_rel_cm", "median_rot_deg", "n_queries")


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
