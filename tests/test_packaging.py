"""The wheel holds the library, the CLI and the shipped encoders, and not the checkout's stage
entry points (they need conf/ and dvc.yaml beside them, so they run from a checkout)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_ships_the_library_not_the_stage_scripts(tmp_path):
    # Built from a copy, so the checkout gets no build/ or egg-info folders.
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "data", "results", "build", "logs",
                                                             "multirun", "*.egg-info", "__pycache__", ".dvc"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path), str(src)], check=True, capture_output=True)
    wheel = next(tmp_path.glob("usvc-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.startswith("usvc-")}
    assert tops == {"usvc"}, tops
    for needed in ("usvc/cli/__init__.py", "usvc/relocalize/relocalizer.py", "usvc/train/options.py"):
        assert needed in names
    assert any(n.startswith("usvc/weights/") and n.endswith(".pt") for n in names)
    # every package of the source tree made it into the wheel
    packages = {p.parent.relative_to(ROOT).as_posix() for p in (ROOT / "usvc").rglob("__init__.py")
                if "__pycache__" not in p.parts}
    assert packages <= {n.rsplit("/", 1)[0] for n in names}
