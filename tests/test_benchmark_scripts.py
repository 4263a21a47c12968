"""Benchmarks that cannot rot: every script in benchmarks/ parses its arguments (`--help` runs its
imports and argument parser), and the ones with a tiny input run it, so a config or API change that
breaks one fails here rather than on the next person who measures."""

from __future__ import annotations

import json
import os
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (REPO / "benchmarks").glob("*.py") if not p.name.startswith("_"))


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_every_benchmark_imports_and_parses_its_arguments(script, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(script.parent))
    monkeypatch.setattr(sys, "argv", [str(script), "--help"])
    with pytest.raises(SystemExit) as exit_:
        runpy.run_path(str(script), run_name="__main__")
    assert exit_.value.code in (0, None)
    assert "usage:" in capsys.readouterr().out


def test_relocalization_speed_runs_every_configured_model(tmp_path):
    """Each conf/model/*.yaml as the stages compose it (a model file sets only what differs)."""
    env = {**os.environ, "USVC_BENCHMARK_DIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "benchmarks/relocalization_speed.py", "--runs", "1", "--warmup", "0",
                           "--sizes", "64x48", "--precision", "fp32"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((tmp_path / "relocalization_speed_cpu.json").read_text())["rows"]
    models = sorted(p.stem for p in (REPO / "conf" / "model").glob("*.yaml"))
    assert [r["model"] for r in rows] == models
    by_model = {r["model"]: r for r in rows}
    assert by_model["default"]["head_width"] == 512 and by_model["small"]["head_width"] == 256
    assert all(r["encoder_ms"] > 0 and r["head_blocks"] >= 0 for r in rows)
