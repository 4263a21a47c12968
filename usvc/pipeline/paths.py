"""Where each stage's artifacts live; dvc.yaml spells the same paths."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ScenePaths:
    data_dir: Path
    results_dir: Path
    scene: str

    @property
    def prepared(self) -> Path:
        return self.data_dir / self.scene / "prepared"

    @property
    def sfm(self) -> Path:
        return self.data_dir / self.scene / "sfm"

    @property
    def keypoints(self) -> Path:
        return self.data_dir / self.scene / "keypoints"

    @property
    def landmarks(self) -> Path:
        return self.data_dir / self.scene / "landmarks"

    def metrics(self, stage: str) -> Path:
        return self.results_dir / self.scene / f"{stage}.json"

    @property
    def buffer(self) -> Path:
        return self.data_dir / self.scene / "buffer"

    @property
    def map(self) -> Path:
        return self.data_dir / self.scene / "map"

    @property
    def relocalize(self) -> Path:
        return self.data_dir / self.scene / "relocalize"

    @property
    def gaussians(self) -> Path:
        return self.data_dir / self.scene / "gaussians"

    @property
    def render(self) -> Path:
        return self.data_dir / self.scene / "render"

    @property
    def plots(self) -> Path:
        return self.results_dir / self.scene / "plots"
