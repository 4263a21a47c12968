"""Typed configuration: Hydra structured-config schemas for every YAML file under conf/.

The YAML files are the single source of values (DVC tracks them directly); these dataclasses
are the schema, so an unknown key or a value of the wrong type fails at compose time, and
`validate` catches values outside their allowed set with a message naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Optional

from hydra.core.config_store import ConfigStore

from usvc.errors import UsvcError
from usvc.synth.params import RoomParams


class ConfigError(UsvcError):
    """A configuration value is outside what the stage accepts."""


@dataclass
class SceneConfig:
    name: str = "???"
    format: str = "???"
    path: str = "???"
    split: str = "???"  # "given" (the format's own split) or "every_nth"
    split_n: int = 8
    metric_scale: Optional[float] = None  # metres per scene unit; null = unknown
    working_width: int = 640  # images are resized to this width before anything else
    generated: bool = False  # produced by stages.generate (the miniature scene)


@dataclass
class SfmConfig:
    max_num_features: int = 4096
    matching: str = "auto"  # auto | exhaustive | sequential | poses
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    pose_pairs_per_image: int = 20
    reconstruction: str = "auto"  # auto | triangulate | incremental
    min_points: int = 100
    num_threads: int = -1


@dataclass
class KeypointsConfig:
    tau: float = 1.5
    sigma: float = 0.15
    weights: str = "uniform"  # uniform | reprojection
    reprojection_scale_px: float = 1.0
    min_track_length: int = 2


@dataclass
class Config:
    seed: int = 0
    data_dir: str = "data"
    results_dir: str = "results"
    scene: SceneConfig = field(default_factory=SceneConfig)
    generate: RoomParams = field(default_factory=RoomParams)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    keypoints: KeypointsConfig = field(default_factory=KeypointsConfig)


_CHOICES: dict[str, tuple[str, ...]] = {
    "scene.format": ("llff", "transforms", "colmap", "ace", "7scenes", "cambridge"),
    "scene.split": ("given", "every_nth"),
    "sfm.matching": ("auto", "exhaustive", "sequential", "poses"),
    "sfm.reconstruction": ("auto", "triangulate", "incremental"),
    "keypoints.weights": ("uniform", "reprojection"),
}
_POSITIVE: tuple[str, ...] = (
    "scene.split_n", "sfm.max_num_features", "sfm.exhaustive_max_images", "sfm.sequential_overlap",
    "sfm.pose_pairs_per_image", "keypoints.sigma", "keypoints.reprojection_scale_px",
    "keypoints.min_track_length",
)


def _get(cfg: Any, dotted: str) -> Any:
    node = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    return node


def validate(cfg: Any) -> None:
    """Reject values outside their allowed set; Hydra has already checked keys and types."""
    for key, choices in _CHOICES.items():
        value = _get(cfg, key)
        if value not in choices:
            raise ConfigError(f"config key {key}={value!r} is not one of {list(choices)}")
    for key in _POSITIVE:
        if not _get(cfg, key) > 0:
            raise ConfigError(f"config key {key}={_get(cfg, key)!r} must be > 0")
    if cfg.keypoints.tau < 0:
        raise ConfigError(f"config key keypoints.tau={cfg.keypoints.tau!r} must be >= 0")
    if cfg.scene.working_width < 0:
        raise ConfigError(f"config key scene.working_width={cfg.scene.working_width!r} must be >= 0 (0 keeps the size)")
    if cfg.scene.metric_scale is not None and not cfg.scene.metric_scale > 0:
        raise ConfigError(f"config key scene.metric_scale={cfg.scene.metric_scale!r} must be > 0 or null")


def register_configs() -> None:
    """Schemas for the primary config and each group, referenced from the YAML defaults lists."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="scene", name="base_scene", node=SceneConfig)
    cs.store(group="generate", name="base_generate", node=RoomParams)
    cs.store(group="sfm", name="base_sfm", node=SfmConfig)
    cs.store(group="keypoints", name="base_keypoints", node=KeypointsConfig)


GROUP_SCHEMAS: dict[str, type] = {
    "scene": SceneConfig,
    "generate": RoomParams,
    "sfm": SfmConfig,
    "keypoints": KeypointsConfig,
}


def schema_fields(schema: type) -> list[str]:
    return [f.name for f in fields(schema)]
