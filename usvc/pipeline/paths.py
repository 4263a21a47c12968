"""Every artifact's name: the folder each stage writes (dvc.yaml spells the same folders) and the
files inside it. Stages, benchmarks and tools take their paths from here, never from literals.

    data/<scene>/<stage>/...      artifacts (DVC outs)
    results/<scene>/<stage>.json  each stage's record (metrics, timings)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

# File names inside the artifact folders: spelled once, in usvc.core.artifact_names.
from usvc.core.artifact_names import (
    BUFFER_H5,
    HOLDOUT_H5,
    KEYPOINTS_H5,
    KEYPOINTS_PLY,
    LANDMARKS_H5,
    MAP_PT,
    METRICS_JSON,
    POINTS_PLY,
    POSES_TXT,
    QUERIES_H5,
    RENDER_H5,
    SCENE_H5,
    SPLAT_CHECK_PNG,
    SPLAT_PLY,
    TRACKS_H5,
)
from usvc.core.scene_names import RESERVED_SCENE_NAMES, SCENE_NAME_RULE, scene_name_problem

__all__ = ["BUFFER_H5", "HOLDOUT_H5", "KEYPOINTS_H5", "KEYPOINTS_PLY", "LANDMARKS_H5", "MAP_PT", "METRICS_JSON",
           "POINTS_PLY", "POSES_TXT", "QUERIES_H5", "RENDER_H5", "SCENE_H5", "SPLAT_CHECK_PNG", "SPLAT_PLY",
           "TRACKS_H5", "RESERVED_SCENE_NAMES", "SCENE_NAME_RULE", "ScenePaths", "scene_name_problem"]


@dataclass(frozen=True)
class ScenePaths:
    data_dir: Path
    results_dir: Path
    scene: str

    @classmethod
    def of_scene_dir(cls, scene_dir: Path, results_dir: Path = Path("results")) -> ScenePaths:
        """The paths of a scene folder given directly (`data/<scene>`, or a sweep job's copy)."""
        scene_dir = Path(scene_dir)
        return cls(scene_dir.parent, Path(results_dir), scene_dir.name)

    @property
    def scene_dir(self) -> Path:
        return self.data_dir / self.scene

    def artifact(self, stage: str) -> Path:
        """The folder a stage writes (train writes `map`)."""
        return getattr(self, "map" if stage == "train" else stage)

    def metrics(self, stage: str) -> Path:
        return self.results_dir / self.scene / f"{stage}.json"

    @property
    def plots(self) -> Path:
        return self.results_dir / self.scene / "plots"

    # Artifact folders, in pipeline order.
    @property
    def prepared(self) -> Path:
        return self.scene_dir / "prepared"

    @property
    def sfm(self) -> Path:
        return self.scene_dir / "sfm"

    @property
    def keypoints(self) -> Path:
        return self.scene_dir / "keypoints"

    @property
    def landmarks(self) -> Path:
        return self.scene_dir / "landmarks"

    @property
    def gaussians(self) -> Path:
        return self.scene_dir / "gaussians"

    @property
    def render(self) -> Path:
        return self.scene_dir / "render"

    @property
    def buffer(self) -> Path:
        return self.scene_dir / "buffer"

    @property
    def map(self) -> Path:
        return self.scene_dir / "map"

    @property
    def relocalize(self) -> Path:
        return self.scene_dir / "relocalize"

    # Files inside them.
    @property
    def scene_file(self) -> Path:
        return self.prepared / SCENE_H5

    @property
    def tracks_file(self) -> Path:
        return self.sfm / TRACKS_H5

    @property
    def keypoints_file(self) -> Path:
        return self.keypoints / KEYPOINTS_H5

    @property
    def landmarks_file(self) -> Path:
        return self.landmarks / LANDMARKS_H5

    @property
    def splat_file(self) -> Path:
        return self.gaussians / SPLAT_PLY

    @property
    def render_file(self) -> Path:
        return self.render / RENDER_H5

    @property
    def buffer_file(self) -> Path:
        return self.buffer / BUFFER_H5

    @property
    def holdout_file(self) -> Path:
        return self.buffer / HOLDOUT_H5

    @property
    def map_file(self) -> Path:
        return self.map / MAP_PT

    @property
    def poses_file(self) -> Path:
        return self.relocalize / POSES_TXT

    @property
    def queries_file(self) -> Path:
        return self.relocalize / QUERIES_H5
