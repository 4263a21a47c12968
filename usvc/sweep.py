"""Hydra callback: after a --multirun sweep, print one table row per job from its metrics.json."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

log = logging.getLogger("usvc")
METRICS_FILE = "metrics.json"


def sweep_table(sweep_dir: Path) -> str:
    """Scalar metrics of every job under `sweep_dir`, as a fixed-width table."""
    rows: list[dict[str, Any]] = []
    for metrics in sorted(Path(sweep_dir).glob(f"*/{METRICS_FILE}"), key=lambda p: int(p.parent.name.split("_")[0])):
        overrides_file = metrics.parent / ".hydra" / "overrides.yaml"
        overrides = overrides_file.read_text().replace("\n", " ").replace("- ", "").strip() if overrides_file.exists() else ""
        values = json.loads(metrics.read_text())
        rows.append({"job": metrics.parent.name.split("_")[0], "overrides": overrides,
                     **{k: v for k, v in values.items() if isinstance(v, (int, float, str))}})
    if not rows:
        return "(no job wrote metrics)"
    cols = list(dict.fromkeys(k for r in rows for k in r))
    cell = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    widths = {c: max(len(c), *(len(cell(r.get(c, ""))) for r in rows)) for c in cols}
    lines = [" | ".join(c.ljust(widths[c]) for c in cols), "-+-".join("-" * widths[c] for c in cols)]
    lines += [" | ".join(cell(r.get(c, "")).ljust(widths[c]) for c in cols) for r in rows]
    return "\n".join(lines)


class SweepSummary(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        table = sweep_table(Path(config.hydra.sweep.dir))
        print(f"\nsweep {config.hydra.sweep.dir}\n{table}\n", flush=True)
