"""A stage's metrics file and its timing file: the one writer and reader of both."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from usvc.core.atomic import atomic_file

# What a run measures about itself rather than about its result: wall times, speeds and memory.
# They differ between two runs that write the same bits, so they go to `<name>.timing.json`
# beside the metrics file, which DVC does not track; the metrics file (tracked in dvc.lock) then
# changes only when the result does, and a rerun on the same kind of machine leaves the lock as
# it was.
TIMING_KEYS = frozenset({"seconds", "peak_memory_mb", "extract_s", "match_s", "reconstruct_s", "train_seconds",
                         "samples_per_second", "fit_seconds", "ms_per_query", "ms_network", "ms_pnp", "ms_refine", "ms_fallback",
                         "query_seconds", "device", "device_name", "query_workers", "query_sift"})


def timing_path(path: Path) -> Path:
    """results/<scene>/train.json -> results/<scene>/train.timing.json"""
    return path.with_name(f"{path.stem}.timing.json")


def write_json(path: Path, payload: dict[str, Any]) -> None:
    """A stage's metrics file: the result's figures in `path`, the run's timings in `timing_path(path)`."""
    figures = {k: v for k, v in payload.items() if k not in TIMING_KEYS}
    timings = {k: v for k, v in payload.items() if k in TIMING_KEYS}
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(figures, indent=2, sort_keys=True) + "\n")
    if timings:
        with atomic_file(timing_path(path)) as tmp:
            tmp.write_text(json.dumps(timings, indent=2, sort_keys=True) + "\n")


def read_metrics(path: Path) -> dict[str, Any]:
    """A stage's figures and, when its timing file is there, its timings, as one dict."""
    values = json.loads(Path(path).read_text())
    timing = timing_path(Path(path))
    if timing.exists():
        values.update(json.loads(timing.read_text()))
    return values
