"""Hydra callback: after a --multirun sweep, print one table row per job from its metrics.json."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from usvc.pipeline.metrics_file import read_metrics
from usvc.pipeline.paths import METRICS_JSON

log = logging.getLogger("usvc")


# Columns after the overrides, in this order when present; every other value follows.
PREFERRED_COLUMNS: tuple[str, ...] = ("acc_*", "median_rot_deg", "median_trans_cm", "median_trans_rel", "initial_acc_*",
                                      "train_seconds", "map_megabytes", "ms_per_query", "kept")


def _natural(key: str) -> list[Any]:
    """acc_1cm_1deg < acc_2cm_2deg < acc_10cm_5deg: numbers compare as numbers."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def column_order(keys: list[str]) -> list[str]:
    """`keys` with PREFERRED_COLUMNS first (a `*` entry: its matches in natural order), then the rest as given."""
    ordered: list[str] = []
    for pattern in PREFERRED_COLUMNS:
        if pattern.endswith("*"):
            ordered += sorted((k for k in keys if k.startswith(pattern[:-1]) and k not in ordered), key=_natural)
        elif pattern in keys and pattern not in ordered:
            ordered.append(pattern)
    return ordered + [k for k in keys if k not in ordered]


def format_table(rows: list[dict[str, Any]]) -> str:
    """Rows of scalars as a fixed-width table: job, overrides, then column_order of the values.

    With several rows, a column outside PREFERRED_COLUMNS that is the same in every row moves to
    one `same in every job:` line under the table, so the table shows what the sweep changed.
    """
    if not rows:
        return "(no job wrote metrics)"
    cell = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    lead = [c for c in ("job", "overrides") if any(c in r for r in rows)]
    cols = lead + column_order([k for k in dict.fromkeys(k for r in rows for k in r) if k not in lead])
    preferred = {c for c in cols if any(c == p or (p.endswith("*") and c.startswith(p[:-1]))
                                        for p in PREFERRED_COLUMNS)}
    constant = [c for c in cols if len(rows) > 1 and c not in lead and c not in preferred
                and all(c in r for r in rows) and len({cell(r[c]) for r in rows}) == 1]
    cols = [c for c in cols if c not in constant]
    widths = {c: max(len(c), *(len(cell(r.get(c, ""))) for r in rows)) for c in cols}
    lines = [" | ".join(c.ljust(widths[c]) for c in cols), "-+-".join("-" * widths[c] for c in cols)]
    lines += [" | ".join(cell(r.get(c, "")).ljust(widths[c]) for c in cols) for r in rows]
    if constant:
        lines.append("same in every job: " + ", ".join(f"{c}={cell(rows[0][c])}" for c in constant))
    return "\n".join(line.rstrip() for line in lines)


def sweep_table(sweep_dir: Path) -> str:
    """Scalar metrics of every job under `sweep_dir`, as a fixed-width table."""
    rows: list[dict[str, Any]] = []
    for metrics in sorted(Path(sweep_dir).glob(f"*/{METRICS_JSON}"), key=lambda p: int(p.parent.name.split("_")[0])):
        overrides_file = metrics.parent / ".hydra" / "overrides.yaml"
        listed = yaml.safe_load(overrides_file.read_text()) if overrides_file.exists() else None
        overrides = " ".join(map(str, listed or []))
        values = read_metrics(metrics)
        rows.append({"job": metrics.parent.name.split("_")[0], "overrides": overrides,
                     **{k: v for k, v in values.items() if isinstance(v, (int, float, str))}})
    return format_table(rows)


class SweepSummary(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        table = sweep_table(Path(config.hydra.sweep.dir))
        print(f"\nsweep {config.hydra.sweep.dir}\n{table}\n", flush=True)
