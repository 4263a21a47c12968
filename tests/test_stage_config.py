"""Each stage reads only its own config: it registers the schemas of the groups it reads, so its
code deps hold exactly those options modules and its params exactly those groups' files (and the
keys it reads of other groups). Editing one step's options reruns that stage and what is
downstream of it, nothing upstream or beside (the DVC run itself: tests/test_pipeline_dvc.py)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from usvc.pipeline import code_deps
from usvc.pipeline.config import GROUP_SCHEMA_NAMES, GROUPS

DVC = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
PRIMARY = yaml.safe_load((REPO / "conf" / "config.yaml").read_text())


def _body(stage: str) -> dict:
    return DVC[stage].get("do", DVC[stage])


def _module(stage: str) -> str:
    return _body(stage)["cmd"].split()[2]


def _descendants(stage: str) -> set[str]:
    """Stages that read (transitively) what `stage` writes, from dvc.yaml's outs and deps."""
    outs = {s: {str(next(iter(o)) if isinstance(o, dict) else o) for o in _body(s).get("outs", [])} for s in DVC}
    deps = {s: set(_body(s).get("deps", [])) for s in DVC}
    found, todo = set(), [stage]
    while todo:
        here = todo.pop()
        for other in DVC:
            if other not in found and outs[here] & deps[other]:
                found.add(other)
                todo.append(other)
    return found


def _registered(stage: str) -> set[str]:
    """The groups the stage's `Stage(...)` call registers (its keyword arguments past the shell's own)."""
    tree = ast.parse((REPO / (_module(stage).replace(".", "/") + ".py")).read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Stage"]
    assert len(calls) == 1, f"{stage}: one Stage(...) call expected"
    return {k.arg for k in calls[0].keywords} - {"artifact", "record", "torch_device", "for_rendered_views"}


def _read_untyped(stage: str) -> set[str]:
    """`cfg.<group>.<key>` reads of groups the stage does not register (plain values from YAML)."""
    src = (REPO / (_module(stage).replace(".", "/") + ".py")).read_text()
    reads = {f"{g}.{k}" for g, k in re.findall(r"cfg\.(\w+)\.(\w+)", src) if g in GROUPS}
    if "for_rendered_views=True" in src:  # the shell reads it for the stage (usvc.pipeline.stage)
        reads.add("buffer.rendered_views")
    return {r for r in reads if r.split(".")[0] not in _registered(stage) and r != "scene.name"}


def _selected(group: str) -> str:
    """The option file conf/config.yaml's defaults list picks for a group."""
    for entry in PRIMARY["defaults"]:
        if isinstance(entry, dict) and group in entry:
            return f"conf/{group}/{entry[group]}.yaml"
    raise AssertionError(f"conf/config.yaml selects no option for {group}")


def _params(stage: str) -> dict[str, tuple[str, ...] | None]:
    out: dict[str, tuple[str, ...] | None] = {}
    for entry in _body(stage).get("params", []):
        for path, keys in entry.items():
            out[path] = None if keys is None else tuple(keys)
    return out


def _options_modules() -> dict[str, Path]:
    return {g: REPO / (GROUP_SCHEMA_NAMES[g].split(":")[0].replace(".", "/") + ".py") for g in GROUPS}


@pytest.mark.parametrize("group", GROUPS)
def test_an_options_edit_reruns_its_stage_and_downstream_only(group):
    module = _options_modules()[group]
    readers = {s for s in DVC if module in code_deps.closure(_module(s))}
    assert readers, f"no stage imports {module.relative_to(REPO)}"
    first = [r for r in readers if readers <= {r} | _descendants(r)]
    assert first, f"{module.relative_to(REPO)} is code of stages beside each other: {sorted(readers)}"
    # the stages it reruns first are ones that read the group (prepare poses unposed scenes with the
    # sfm group's settings, so it comes before sfm), never one that merely imports the module
    assert all(group in _registered(r) for r in first), (group, first)
    owner = module.parent.name
    if owner in DVC:
        assert owner in readers, f"{module.relative_to(REPO)} is not code of its own stage {owner}"


def test_options_modules_are_code_of_the_stages_that_register_them():
    for stage in DVC:
        closure = code_deps.closure(_module(stage))
        imported = {g for g, path in _options_modules().items() if path in closure}
        # an options module may come along with a step's code only if the stage registers its group
        # or it is the step's own input check; never a group the stage neither reads nor needs
        assert _registered(stage) <= imported, (stage, _registered(stage), imported)


@pytest.mark.parametrize("stage", sorted(DVC))
def test_params_track_what_the_stage_reads(stage):
    params = _params(stage)
    registered = _registered(stage)
    whole = {p for p, keys in params.items() if keys is None}
    for group in registered:
        want = "conf/scene/${item}.yaml" if group == "scene" else _selected(group)
        assert want in whole, f"{stage} reads the {group} group but does not track {want}"
    for read in _read_untyped(stage):
        group, key = read.split(".")
        if group == "scene":
            continue  # the scene file is tracked whole where a stage reads it (generate)
        file = _selected(group)
        assert file in whole or key in (params.get(file) or ()), f"{stage} reads {read} but does not track it"
    groups_tracked = {Path(p).parts[1] for p in whole if Path(p).parts[1] != "scene"}
    assert groups_tracked <= registered | {"generate"} | {"scene"}, (stage, groups_tracked, registered)


def test_a_stage_tracks_only_the_option_file_its_config_selects():
    for stage in DVC:
        for path, keys in _params(stage).items():
            parts = Path(path).parts
            if parts[1] in ("scene", "method") or path == "conf/config.yaml":
                continue
            assert path == _selected(parts[1]), f"{stage} tracks {path}, which conf/config.yaml does not select"


def test_every_group_is_read_by_some_stage():
    assert set(GROUPS) <= set().union(*(_registered(s) for s in DVC))


def test_a_stage_refuses_a_key_of_a_group_it_does_not_read(tmp_path):
    """Groups a stage does not register compose as plain values, yet a misspelt key of one is still
    named (their keys come from the group's YAML files)."""
    from hydra import compose, initialize_config_dir

    from usvc.pipeline.config import ConfigError, register_configs, validate
    from usvc.train.options import TrainOptions

    schemas = register_configs({"train": TrainOptions})
    try:
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
            cfg = compose(config_name="config", overrides=["scene=mini", "+render.viewz=3"])
        with pytest.raises(ConfigError, match=r"render\.viewz .*did you mean render\.views"):
            validate(cfg, schemas)
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
            cfg = compose(config_name="config", overrides=["scene=mini", "render.views=3"])
        validate(cfg, schemas)  # a real key of an unread group is fine
        assert not hasattr(cfg.render, "problems") and cfg.train.bundle_weight == 0.25
    finally:
        register_configs()  # the other tests compose with every group typed
