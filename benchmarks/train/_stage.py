"""The `train` stage as the train family's stage benchmarks run it: in a scratch data folder holding
copies of a scene's buffer and SfM tracks under other names, each run a process of its own."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from benchmarks._report import ROOT


def train_command(scene: str, name: str, data: Path, iterations: int, threads: str) -> list[str]:
    """`python -m stages.train` for the copy `name` of `scene` in the scratch folder `data`."""
    return [sys.executable, "-m", "stages.train", f"scene={scene}", f"scene.name={name}", f"data_dir={data}",
            f"results_dir={data / 'results'}", f"hydra.run.dir={data / 'logs' / name}",
            f"train.iterations={iterations}", f"threads={threads}"]


def copy_scene(scene: str, data: Path, names: tuple[str, ...]) -> None:
    """The scene's buffer and SfM tracks copied into `data`, once per name; a scene without them stops
    the benchmark with the one line saying so."""
    src = ROOT / "data" / scene
    for sub in ("buffer", "sfm"):
        if not (src / sub).is_dir():
            raise SystemExit(f"{src / sub} is missing: run the pipeline up to the buffer stage first")
    for name in names:
        for sub in ("buffer", "sfm"):
            shutil.copytree(src / sub, data / name / sub)
