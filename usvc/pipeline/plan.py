"""Which DVC stages a Hydra override makes stale, read from dvc.yaml (pure: no I/O past reading it).

dvc.yaml tracks, per stage, the conf/ files (or top-level keys of them) the stage composes, so
the stages a config override can change are exactly the ones that track where its value lives:

- `group.key=value` (keypoints.tau, train.bundle_weight): stages that track a file under
  conf/<group>/, or top-level key <group> of any conf file (the `# @package _global_` method
  files are tracked per key: `conf/method/single.yaml: [train]`).
- `group=option` (model=small, method=single): stages that track a file under conf/<group>/.
- `key=value` for a top-level key of the primary config (seed): stages that track that key
  (`conf/config.yaml: [seed]`) or the whole primary config.
- `scene=` picks the scene and changes nothing by itself; hydra.*, data_dir and results_dir
  only move files around.

A stage without `foreach` (generate) makes the bundled generated scene and applies to it only.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from usvc.core.errors import UsvcError

CONF_DIR = "conf"
PRIMARY_CONFIG = f"{CONF_DIR}/config.yaml"
SCENE_KEY = "scene"  # `scene=<name>` selects what to run on
IGNORED_KEYS = frozenset({"data_dir", "results_dir"})
_ARTIFACT = re.compile(r"^data/\$\{item\}/([^/]+)$")
_MODULE = re.compile(r"-m\s+(\S+)")


class PlanError(UsvcError):
    """An override no stage reads, or a sweep that changes nothing."""


@dataclass(frozen=True)
class StagePlan:
    name: str
    per_scene: bool  # defined with foreach: one stage per scene (`<name>@<scene>`)
    module: str  # the entry point its cmd runs (stages.<name>)
    params: tuple[tuple[str, tuple[str, ...] | None], ...]  # (file, keys); None = the whole file
    artifacts: tuple[str, ...]  # <name> of each `data/${item}/<name>` out

    def target(self, scene: str) -> str:
        """The DVC stage name `dvc repro` takes for this scene."""
        return f"{self.name}@{scene}" if self.per_scene else self.name

    def applies_to(self, generated: bool) -> bool:
        """Per-scene stages run for every scene; the others only make the generated scene."""
        return self.per_scene or generated


Plan = tuple[StagePlan, ...]


def _params(entries: Iterable[Any]) -> tuple[tuple[str, tuple[str, ...] | None], ...]:
    out: list[tuple[str, tuple[str, ...] | None]] = []
    for entry in entries or []:
        if isinstance(entry, str):  # a bare key of params.yaml
            out.append(("params.yaml", (entry,)))
            continue
        for path, keys in entry.items():
            if keys is None:
                out.append((str(path), None))
            else:
                out.append((str(path), tuple(str(k) for k in ([keys] if isinstance(keys, str) else keys))))
    return tuple(out)


def _out_paths(entries: Iterable[Any]) -> list[str]:
    paths: list[str] = []
    for entry in entries or []:
        paths.extend([entry] if isinstance(entry, str) else [str(k) for k in entry])
    return paths


def parse_plan(dvc: dict[str, Any]) -> Plan:
    """Every stage of a parsed dvc.yaml, in file order."""
    stages: list[StagePlan] = []
    for name, stage in (dvc.get("stages") or {}).items():
        per_scene = "foreach" in stage
        body = stage.get("do", {}) if per_scene else stage
        module = _MODULE.search(str(body.get("cmd", "")))
        artifacts = tuple(m.group(1) for p in _out_paths(body.get("outs")) if (m := _ARTIFACT.match(p)))
        stages.append(StagePlan(name=str(name), per_scene=per_scene,
                                module=module.group(1) if module else f"stages.{name}",
                                params=_params(body.get("params")), artifacts=artifacts))
    return tuple(stages)


def load_plan(dvc_yaml: Path | str) -> Plan:
    return parse_plan(yaml.safe_load(Path(dvc_yaml).read_text()))


def override_key(override: str) -> str | None:
    """The config key an override sets (`++train.lr=1` -> train.lr); None when it changes no stage."""
    key = override.split("=", 1)[0].strip().lstrip("~+").split("@", 1)[0]
    if not key or key == SCENE_KEY or key in IGNORED_KEYS or key == "hydra" or key.startswith(("hydra.", "hydra/")):
        return None
    return key


def _groups(plan: Plan) -> set[str]:
    """Config groups: the directories under conf/ that hold a tracked file."""
    return {parts[1] for st in plan for path, _ in st.params
            if len(parts := path.split("/")) > 2 and parts[0] == CONF_DIR}


def _key_overlaps(tracked: str, key: str) -> bool:
    """Does a tracked (dotted) key cover `key`, or a part of it? seed ~ seed, train ~ train.lr."""
    a, b = tracked.split("."), key.split(".")
    n = min(len(a), len(b))
    return a[:n] == b[:n]


def _reads(stage: StagePlan, key: str, groups: set[str]) -> bool:
    head = key.split(".")[0]
    group_dir = f"{CONF_DIR}/{head}/"
    dotted = "." in key
    for path, keys in stage.params:
        if (dotted or head in groups) and path.startswith(group_dir):
            if keys is None or not dotted:
                return True
            # a group file tracked for some keys only (render: gaussians.tile) reads just those
            if any(_key_overlaps(k, key.split(".", 1)[1]) for k in keys):
                return True
            continue
        if head in groups and not dotted:
            continue  # `group=option`: only the group's files say which option a stage composed
        if keys is None:
            if not dotted and path == PRIMARY_CONFIG:
                return True
        elif path.startswith(f"{CONF_DIR}/") and any(_key_overlaps(k, key) for k in keys):
            return True
    return False


def stages_reading(key: str, plan: Plan) -> list[str]:
    """Stages (file order) whose tracked params include the config value `key` sets."""
    groups = _groups(plan)
    return [st.name for st in plan if _reads(st, key, groups)]


def first_affected_stage(overrides: Sequence[str], plan: Plan, generated: bool = True) -> str:
    """The earliest stage (dvc.yaml order) that any override changes, for a scene.

    `generated`: whether the scene is the generated one (stages without foreach apply to it only).
    Raises PlanError for an override no stage reads, and when no override changes any stage.
    """
    order = {st.name: i for i, st in enumerate(plan)}
    by_name = {st.name: st for st in plan}
    first: str | None = None
    for override in overrides:
        key = override_key(override)
        if key is None:
            continue
        readers = stages_reading(key, plan)
        if not readers:
            raise PlanError(f"no stage reads {key} (override {override!r}): dvc.yaml tracks it nowhere")
        applicable = [s for s in readers if by_name[s].applies_to(generated)]
        if not applicable:
            raise PlanError(f"{key} is read only by stage(s) {', '.join(readers)}, which run only for the "
                            "generated scene, not this one")
        if first is None or order[applicable[0]] < order[first]:
            first = applicable[0]
    if first is None:
        given = " ".join(overrides) or "(none)"
        raise PlanError(f"nothing to sweep: no override changes a pipeline stage (got: {given}); "
                        "give a config value, e.g. keypoints.tau=1.0,1.5,2.0")
    return first


def split_plan(plan: Plan, first: str, generated: bool = True) -> tuple[Plan, Plan]:
    """(upstream stages to reuse, stages to rerun: `first` and every later one), for the scene."""
    names = [st.name for st in plan]
    if first not in names:
        raise PlanError(f"dvc.yaml has no stage {first!r}")
    i = names.index(first)
    keep = lambda sts: tuple(st for st in sts if st.applies_to(generated))  # noqa: E731
    return keep(plan[:i]), keep(plan[i:])
