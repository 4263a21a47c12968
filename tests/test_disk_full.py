"""A full disk or a file-size limit while a stage writes: one line, no artifact, no temporary files."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import REPO

pytestmark = pytest.mark.slow



def _run_limited(limit: int, stage: str, *overrides: str) -> subprocess.CompletedProcess:
    code = (f"import resource, runpy, sys\n"
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
            f"sys.argv = ['{stage}', *sys.argv[1:]]\n"
            f"runpy.run_module('stages.{stage}', run_name='__main__')\n")
    return subprocess.run([sys.executable, "-c", code, *overrides], cwd=REPO, capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    """The miniature scene's raw frames (small: 2 map sequences of 6 frames)."""
    root = tmp_path_factory.mktemp("full")
    proc = subprocess.run([sys.executable, "-m", "stages.generate", "scene=mini", f"scene.path={root / 'raw'}",
                           "generate.frames_per_map_sequence=6", "generate.n_query_frames=2",
                           f"results_dir={root / 'results'}", f"hydra.run.dir={root / 'log'}"],
                          cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return root / "raw"


@pytest.mark.parametrize("limit", [20_000, 200_000])
def test_prepare_under_a_file_size_limit(raw, tmp_path, limit):
    """20 kB: an image write fails; 200 kB: scene.h5 fails (it used to crash the interpreter)."""
    proc = _run_limited(limit, "prepare", "scene=mini", f"scene.path={raw}", f"data_dir={tmp_path / 'data'}",
                        f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "Traceback" not in out and "Segmentation" not in out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1, out
    assert "File too large" in errors[0] or "cannot write" in errors[0], errors[0]
    # the destination folder and the reason, never the temporary path (gone by the time it is read)
    assert f"in {tmp_path / 'data' / 'mini' / 'prepared'}: File too large" in errors[0], errors[0]
    assert ".tmp-" not in errors[0], errors[0]
    leftovers = [p for p in (tmp_path / "data").rglob("*")] if (tmp_path / "data").exists() else []
    assert all(p.is_dir() for p in leftovers), leftovers  # at most the empty scene folder
    assert not (tmp_path / "results" / "mini" / "prepared.json").exists()
