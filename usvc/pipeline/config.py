"""The pipeline's configuration: each config group's schema is its step's options dataclass.

`conf/<group>/*.yaml` hold the values (DVC tracks them directly); the options dataclass beside each
step's code (e.g. `usvc/train/options.py`) is the group's schema and the type the step's code
takes. Each stage registers the schemas of the groups it reads (`register_configs({...})`, see
`usvc.pipeline.stage.Stage`) and nothing else, so a stage imports, and DVC reruns it for, only
its own options modules; the other groups compose as plain values. An unknown key or a value of
the wrong type fails at compose time; `validate` asks each registered group's options for values
outside what the step accepts (`problems()`) and names the key.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import yaml
from hydra.core.config_store import ConfigStore

from usvc.core.errors import UsvcError

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


class ConfigError(UsvcError):
    """A configuration value is outside what the stage accepts."""


@dataclass
class Config:
    seed: int = 0  # mapping seed: buffer sampling, head initialisation, RANSAC at query time
    threads: str = "auto"  # torch/OpenCV/COLMAP/BLAS threads: auto (cores / jobs side by side) or a number
    device: str = "auto"  # torch's device for the stages that run it: auto (CUDA where torch sees one) | cpu | cuda | cuda:N
    query_workers: str = "auto"  # photos the relocalize stage localizes at a time, each with threads // query_workers threads: auto (= threads, one each) or a number
    method: str = "multiview"  # set by the method group: single | multiview | multiview_gs
    data_dir: str = "data"  # where the artifacts go: <data_dir>/<scene>/<stage>
    results_dir: str = "results"  # where the metrics and plots go: <results_dir>/<scene>/
    # One entry per config group: its schema is registered by the stage that reads it.
    scene: Any = None  # the scene group: SceneOptions
    generate: Any = None  # the generate group: RoomParams
    sfm: Any = None  # the sfm group: SfmOptions
    keypoints: Any = None  # the keypoints group: KeypointOptions
    landmarks: Any = None  # the landmarks group: LandmarksOptions
    model: Any = None  # the model group: ModelOptions
    buffer: Any = None  # the buffer group: BufferOptions
    train: Any = None  # the train group: TrainOptions
    relocalize: Any = None  # the relocalize group: RelocalizeOptions
    gaussians: Any = None  # the gaussians group: GaussiansOptions
    render: Any = None  # the render group: RenderOptions


METHODS = ("single", "multiview", "multiview_gs")
TOP_LEVEL = ("seed", "threads", "device", "query_workers", "method", "data_dir", "results_dir")

# Each config group's schema: the options dataclass of its step, beside the step's code. Named, not
# imported: a stage imports the ones it reads (tools and tests load them all with `group_schemas`).
GROUP_SCHEMA_NAMES: dict[str, str] = {
    "scene": "usvc.prepare.options:SceneOptions",
    "generate": "usvc.generate.params:RoomParams",
    "sfm": "usvc.sfm.options:SfmOptions",
    "keypoints": "usvc.keypoints.options:KeypointOptions",
    "landmarks": "usvc.landmarks.options:LandmarksOptions",
    "model": "usvc.model.options:ModelOptions",
    "buffer": "usvc.buffer.options:BufferOptions",
    "train": "usvc.train.options:TrainOptions",
    "relocalize": "usvc.relocalize.options:RelocalizeOptions",
    "gaussians": "usvc.gaussians.options:GaussiansOptions",
    "render": "usvc.render.options:RenderOptions",
}
GROUPS = tuple(GROUP_SCHEMA_NAMES)


def group_schemas(groups: Any = None) -> dict[str, type]:
    """Group -> options dataclass, for the named groups (default: all), in pipeline order."""
    out: dict[str, type] = {}
    for group in GROUPS if groups is None else groups:
        module, name = GROUP_SCHEMA_NAMES[group].split(":")
        out[group] = getattr(importlib.import_module(module), name)
    return out


def register_configs(schemas: dict[str, type] | None = None) -> dict[str, type]:
    """Register the primary config and each group's base node: the given schemas (default: all of
    them) typed, every other group an open node that takes its YAML values as they are. Returns the
    typed schemas."""
    schemas = group_schemas() if schemas is None else dict(schemas)
    unknown = sorted(set(schemas) - set(GROUPS))
    if unknown:
        raise ValueError(f"not config groups: {unknown}")
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    for group in GROUPS:
        cs.store(group=group, name=f"base_{group}", node=schemas.get(group, {}))
    return schemas


def _yaml_keys(group: str) -> set[str]:
    """Keys any of the group's YAML files sets (the keys of a group a stage does not read)."""
    keys: set[str] = set()
    for path in (CONF_DIR / group).glob("*.yaml"):
        data = yaml.safe_load(path.read_text()) or {}
        keys.update(k for k in data if k != "defaults")
    return keys


def _known_keys(schemas: dict[str, type]) -> list[str]:
    top = [f.name for f in fields(Config)]
    known = [f"{g}.{f.name}" for g, schema in schemas.items() for f in fields(schema)]
    return top + known + [f"{g}.{k}" for g in GROUPS if g not in schemas for k in sorted(_yaml_keys(g))]


def _check_keys(cfg: Any, schemas: dict[str, type]) -> None:
    """Every key must be one of the schema's: Hydra's `+key=value` (and `++`) can add keys that the
    schema does not have, which the stages would otherwise ignore or trip over deep inside."""
    import difflib

    from omegaconf import DictConfig

    if not isinstance(cfg, DictConfig):
        return
    known = _known_keys(schemas)
    found = [k for k in cfg.keys() if k != "hydra"]
    found += [f"{g}.{k}" for g in GROUPS if isinstance(cfg.get(g), DictConfig) for k in cfg[g].keys()]
    for key in found:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"config key {key} is not a setting of usvc{hint}")


def group_options(cfg: Any, group: str) -> Any:
    """The options object of one config group (an instance of its step's options dataclass when
    the group's schema is registered): how a stage turns its config into the options its step takes."""
    from omegaconf import DictConfig, OmegaConf

    node = cfg[group]
    return OmegaConf.to_object(node) if isinstance(node, DictConfig) else node


def _check_scene_name(cfg: Any) -> None:
    """`scene.name` names the folders every stage writes (data/<name>/, results/<name>/): the rule of
    `usvc map --name` (usvc.pipeline.paths.scene_name_problem), checked before anything is written."""
    scene = cfg.get("scene") if hasattr(cfg, "get") else None
    if scene is None or not hasattr(scene, "get") or "name" not in scene:
        return
    from usvc.pipeline.paths import scene_name_problem

    why = scene_name_problem(scene.name)
    if why:
        sep = " " if why.startswith("is ") else ": "
        raise ConfigError(f"config key scene.name={scene.name!r}{sep}{why}")


def validate(cfg: Any, schemas: dict[str, type] | None = None) -> None:
    """Reject unknown keys and values outside what each step accepts (Hydra has checked the types):
    each registered group's options dataclass says what it accepts (`problems()`). `schemas`: the
    groups the caller registered (default: all)."""
    schemas = group_schemas() if schemas is None else schemas
    _check_keys(cfg, schemas)
    _check_scene_name(cfg)
    if cfg.method not in METHODS:
        raise ConfigError(f"config key method={cfg.method!r} is not one of {list(METHODS)}")
    for group in schemas:
        problems = group_options(cfg, group).problems()
        if problems:
            raise ConfigError("; ".join(f"config key {group}.{p}" for p in problems))
    try:
        from usvc.pipeline.threads import resolve

        resolve(cfg.threads)
    except ValueError as err:
        raise ConfigError(f"config key {err}") from None
    try:
        from usvc.pipeline.threads import query_workers

        query_workers(cfg.query_workers, 1)
    except ValueError as err:
        raise ConfigError(f"config key {err}") from None
    from usvc.core.device import device_problem

    if device_problem(cfg.device):
        raise ConfigError(f"config key {device_problem(cfg.device)}")


def compose_for_script(scene: str, overrides: list[str]) -> Any:
    """The config a stage would see for ``scene=<scene> <overrides>``, for scripts outside Hydra's
    entry points (benchmarks): every group typed, the same validation."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    register_configs()
    asked = [f"scene={scene}", *overrides]
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            cfg = compose(config_name="config", overrides=asked)
    except HydraException as e:  # an unknown scene or option, a malformed override: one line naming it
        lines = [line.strip() for line in str(e).splitlines() if line.strip()]
        why = lines[0] if lines else type(e).__name__
        if len(lines) > 1 and lines[1].startswith("Available options"):  # an unknown scene or option: the choices
            choices = []
            for line in lines[2:]:
                if line.startswith("Config search path"):
                    break
                choices.append(line)
            why += f" ({lines[1].rstrip(':').lower()}: {', '.join(choices[:20])})"
        raise UsvcError(f"config {' '.join(asked)}: {why}") from None
    validate(cfg)
    return cfg
