"""What git and DVC track under results/: every small file dvc.yaml declares, and no run timings.

`dvc exp show/diff` and `dvc plots diff` read a commit's results/ files from git, so each
`cache: false` file of dvc.yaml must not be git-ignored; `dvc metrics show` prints only the
headline file, so `metrics:` lists nothing else.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from usvc.metrics.evaluate import HEADLINE_FILE
from usvc.pipeline.metrics_file import timing_path

STAGES = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
SCENE = "mini"


def _entries(stage: dict, section: str) -> list[tuple[str, dict]]:
    body = stage.get("do", stage)
    out = []
    for entry in body.get(section) or []:
        if isinstance(entry, str):
            out.append((entry.replace("${item}", SCENE), {}))
        else:
            out += [(path.replace("${item}", SCENE), opts or {}) for path, opts in entry.items()]
    return out


def _ignored(paths: list[str]) -> set[str]:
    """The paths git would ignore (whether or not they exist)."""
    proc = subprocess.run(["git", "check-ignore", "--no-index", "--stdin"], cwd=REPO, input="\n".join(paths),
                          capture_output=True, text=True)
    assert proc.returncode in (0, 1), proc.stderr  # 1: none ignored
    return set(proc.stdout.split())


UNCACHED = sorted({p for st in STAGES.values() for section in ("outs", "metrics", "plots")
                   for p, opts in _entries(st, section) if opts.get("cache") is False})


def test_every_uncached_file_is_under_results():
    assert UNCACHED and all(p.startswith(f"results/{SCENE}/") for p in UNCACHED)


def test_git_tracks_every_file_dvc_yaml_declares_uncached():
    ignored = _ignored(UNCACHED + [p.replace(f"/{SCENE}/", "/kitchen/") for p in UNCACHED])
    assert not ignored, f"dvc.yaml declares these with cache: false, but .gitignore ignores them: {sorted(ignored)}"


def test_git_ignores_timings_and_anything_else_under_results():
    timings = [str(timing_path(p)) for p in map(Path, UNCACHED) if p.suffix == ".json"]
    others = ["results/mini/diagnosis.json", "results/mini/plots/extra.png", "results/mini/sub/metrics.json",
              "results/notes.json", "results/benchmarks/run.timing.json"]
    assert _ignored(timings + others) == set(timings + others)
    assert not _ignored(["results/benchmarks/pipeline_fresh.json"])  # quoted by the docs


def test_metrics_lists_only_the_headline():
    metrics = [p for st in STAGES.values() for p, _ in _entries(st, "metrics")]
    assert metrics == [f"results/{SCENE}/{HEADLINE_FILE}"]


@pytest.mark.parametrize("name", sorted(STAGES))
def test_each_stage_keeps_its_figures_file(name):
    """Per-stage figures left `metrics:` for `outs:` (uncached): still in dvc.lock and git, off the default table."""
    outs = [p for p, opts in _entries(STAGES[name], "outs") if opts.get("cache") is False]
    assert any(p.endswith(".json") for p in outs), f"stage {name} declares no uncached figures file"
