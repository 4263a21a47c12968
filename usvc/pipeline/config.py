"""The pipeline's configuration: each config group's schema is its step's options dataclass.

`conf/<group>/*.yaml` hold the values (DVC tracks them directly); the options dataclass beside each
step's code (e.g. `usvc/train/options.py`) is the group's schema and the type the step's code
takes, with defaults equal to `conf/<group>/default.yaml` (a test checks). An unknown key or a
value of the wrong type fails at compose time; `validate` asks each group's options for values
outside what the step accepts (`problems()`) and names the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from hydra.core.config_store import ConfigStore

from usvc.buffer.options import BufferOptions
from usvc.core.errors import UsvcError
from usvc.gaussians.options import GaussiansOptions
from usvc.generate.params import RoomParams
from usvc.keypoints.options import KeypointOptions
from usvc.landmarks.options import LandmarksOptions
from usvc.model.options import ModelOptions
from usvc.prepare.options import SceneOptions
from usvc.relocalize.options import RelocalizeOptions
from usvc.render.options import RenderOptions
from usvc.sfm.options import SfmOptions
from usvc.train.options import TrainOptions


class ConfigError(UsvcError):
    """A configuration value is outside what the stage accepts."""


@dataclass
class Config:
    seed: int = 0  # mapping seed: buffer sampling, head initialisation, RANSAC at query time
    threads: str = "auto"  # torch/OpenCV/COLMAP/BLAS threads: auto (cores / jobs side by side) or a number
    method: str = "multiview"  # set by the method group: single | multiview | multiview_gs
    data_dir: str = "data"  # where the artifacts go: <data_dir>/<scene>/<stage>
    results_dir: str = "results"  # where the metrics and plots go: <results_dir>/<scene>/
    scene: SceneOptions = field(default_factory=SceneOptions)  # the scene group: SceneOptions
    generate: RoomParams = field(default_factory=RoomParams)  # the generate group: RoomParams
    sfm: SfmOptions = field(default_factory=SfmOptions)  # the sfm group: SfmOptions
    keypoints: KeypointOptions = field(default_factory=KeypointOptions)  # the keypoints group: KeypointOptions
    landmarks: LandmarksOptions = field(default_factory=LandmarksOptions)  # the landmarks group: LandmarksOptions
    model: ModelOptions = field(default_factory=ModelOptions)  # the model group: ModelOptions
    buffer: BufferOptions = field(default_factory=BufferOptions)  # the buffer group: BufferOptions
    train: TrainOptions = field(default_factory=TrainOptions)  # the train group: TrainOptions
    relocalize: RelocalizeOptions = field(default_factory=RelocalizeOptions)  # the relocalize group: RelocalizeOptions
    gaussians: GaussiansOptions = field(default_factory=GaussiansOptions)  # the gaussians group: GaussiansOptions
    render: RenderOptions = field(default_factory=RenderOptions)  # the render group: RenderOptions


METHODS = ("single", "multiview", "multiview_gs")


def _known_keys() -> list[str]:
    top = [f.name for f in fields(Config)]
    return top + [f"{g}.{f.name}" for g, schema in GROUP_SCHEMAS.items() for f in fields(schema)]


def _check_keys(cfg: Any) -> None:
    """Every key must be one of the schema's: Hydra's `+key=value` (and `++`) can add keys that the
    schema does not have, which the stages would otherwise ignore or trip over deep inside."""
    import difflib

    from omegaconf import DictConfig

    if not isinstance(cfg, DictConfig):
        return
    known = _known_keys()
    found = [k for k in cfg.keys() if k != "hydra"]
    found += [f"{g}.{k}" for g in GROUP_SCHEMAS if isinstance(cfg.get(g), DictConfig) for k in cfg[g].keys()]
    for key in found:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"config key {key} is not a setting of usvc{hint}")


def group_options(cfg: Any, group: str) -> Any:
    """The options object of one config group (an instance of its step's options dataclass): how
    every stage turns its config into the options its step's code takes."""
    from omegaconf import DictConfig, OmegaConf

    node = cfg[group]
    return OmegaConf.to_object(node) if isinstance(node, DictConfig) else node


def validate(cfg: Any) -> None:
    """Reject unknown keys and values outside what each step accepts (Hydra has checked the types):
    each group's options dataclass says what it accepts (`problems()`)."""
    _check_keys(cfg)
    if cfg.method not in METHODS:
        raise ConfigError(f"config key method={cfg.method!r} is not one of {list(METHODS)}")
    for group in GROUP_SCHEMAS:
        problems = group_options(cfg, group).problems()
        if problems:
            raise ConfigError("; ".join(f"config key {group}.{p}" for p in problems))
    try:
        from usvc.pipeline.threads import resolve

        resolve(cfg.threads)
    except ValueError as err:
        raise ConfigError(f"config key {err}") from None


# Each config group's schema: the options dataclass of its step, beside the step's code.
GROUP_SCHEMAS: dict[str, type] = {
    "scene": SceneOptions,
    "generate": RoomParams,
    "sfm": SfmOptions,
    "keypoints": KeypointOptions,
    "landmarks": LandmarksOptions,
    "model": ModelOptions,
    "buffer": BufferOptions,
    "train": TrainOptions,
    "relocalize": RelocalizeOptions,
    "gaussians": GaussiansOptions,
    "render": RenderOptions,
}


def register_configs() -> None:
    """Schemas for the primary config and each group, referenced from the YAML defaults lists."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    for group, schema in GROUP_SCHEMAS.items():
        cs.store(group=group, name=f"base_{group}", node=schema)




def compose_for_script(scene: str, overrides: list[str]) -> Any:
    """The config a stage would see for ``scene=<scene> <overrides>``, for scripts outside Hydra's
    entry points (benchmarks): the same schema and the same validation."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    register_configs()
    conf_dir = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf_dir), version_base=None):
        cfg = compose(config_name="config", overrides=[f"scene={scene}", *overrides])
    validate(cfg)
    return cfg
