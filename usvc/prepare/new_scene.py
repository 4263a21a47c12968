"""Add a scene to a usvc checkout in one step: its photos under ``data/raw/<name>``, its
``conf/scene/<name>.yaml``, its name in ``params.yaml``, then (optionally) ``dvc repro`` of it.

This is what ``usvc map PHOTOS --name NAME`` runs. The capture is imported once up front
(:func:`usvc.prepare.importers.load_scene`) so a wrong folder or format fails before anything is written.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import yaml

from usvc.core.errors import UsvcError
from usvc.prepare.importers import FORMATS, load_scene

log = logging.getLogger(__name__)

NAME_RULE = re.compile(r"^[a-z][a-z0-9_]*$")


@dataclass(frozen=True)
class NewSceneOptions:
    name: str
    format: str = "images"
    split_n: int = 8  # every split_n-th photo is a query (never trained on)
    working_width: int = 640
    metric_scale: float | None = None  # metres per scene unit, when the poses are metric


def find_checkout(start: Path) -> Path:
    """The usvc checkout containing ``start`` (where dvc.yaml, params.yaml and conf/scene are)."""
    for folder in (start, *start.parents):
        if (folder / "dvc.yaml").is_file() and (folder / "params.yaml").is_file() and (folder / "conf" / "scene").is_dir():
            return folder
    raise UsvcError(f"{start} is not inside a usvc checkout (no dvc.yaml, params.yaml and conf/scene/ above it); "
                    "run `usvc map` from the repository")


def _scene_yaml(source: Path, opts: NewSceneOptions) -> str:
    scale = "null" if opts.metric_scale is None else repr(float(opts.metric_scale))
    return (f"# Added by `usvc map` from {source}\n"
            "defaults:\n  - base_scene\n  - _self_\n"
            f"name: {opts.name}\nformat: {opts.format}\npath: data/raw/{opts.name}\n"
            f"split: every_nth\nsplit_n: {opts.split_n}\nmetric_scale: {scale}\n"
            f"working_width: {opts.working_width}\nundistort_fov: crop\ngenerated: false\n")


def _add_to_params(params: Path, name: str) -> None:
    """Append ``name`` to the ``scenes:`` list of params.yaml, keeping its comments."""
    lines = params.read_text().splitlines(keepends=True)
    try:
        start = next(i for i, line in enumerate(lines) if line.rstrip() == "scenes:")
    except StopIteration:
        raise UsvcError(f"{params}: no top-level 'scenes:' list to add the scene to") from None
    end = start + 1
    while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
        end += 1
    while end > start + 1 and not lines[end - 1].strip():
        end -= 1
    indent = next((re.match(r"\s*", line).group(0) for line in lines[start + 1:end] if line.strip()), "  ")
    if end == len(lines) and lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    lines.insert(end, f"{indent}- {name}\n")
    text = "".join(lines)
    if name not in (yaml.safe_load(text) or {}).get("scenes", []):
        raise UsvcError(f"{params}: could not add {name!r} to 'scenes' (is it a block list?)")
    tmp = params.with_name(params.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, params)


def _copy_tree(src: Path, dst: Path) -> None:
    """Hard links where the file system allows them (no second copy of the photos), else copies."""
    def link_or_copy(a: str, b: str) -> None:
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    shutil.copytree(src, dst, copy_function=link_or_copy)


def add_scene(source: Path, checkout: Path, opts: NewSceneOptions) -> dict:
    """Import check, then data/raw/<name>, conf/scene/<name>.yaml and params.yaml; returns what was written."""
    source = source.resolve()
    if not NAME_RULE.match(opts.name):
        raise UsvcError(f"scene name {opts.name!r}: use lower-case letters, digits and _, starting with a letter")
    if opts.format not in FORMATS:
        raise UsvcError(f"format {opts.format!r} is not one of {list(FORMATS)}")
    if opts.split_n < 2:
        raise UsvcError(f"split_n={opts.split_n}: need >= 2 (every split_n-th photo is a query)")
    if not source.is_dir():
        raise UsvcError(f"{source} is not a folder")
    conf = checkout / "conf" / "scene" / f"{opts.name}.yaml"
    raw = checkout / "data" / "raw" / opts.name
    params = checkout / "params.yaml"
    scenes = (yaml.safe_load(params.read_text()) or {}).get("scenes", [])
    for taken, what in ((conf.exists(), str(conf)), (raw.exists(), str(raw)), (opts.name in scenes, "params.yaml scenes")):
        if taken:
            raise UsvcError(f"scene {opts.name!r} already exists ({what}); pick another --name")
    scene = load_scene(opts.format, source, opts.name, "every_nth", opts.split_n, opts.metric_scale)
    n_query = sum(f.split == "test" for f in scene.frames)
    raw.parent.mkdir(parents=True, exist_ok=True)
    tmp = raw.with_name(f".{opts.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _copy_tree(source, tmp)
        os.replace(tmp, raw)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    conf.write_text(_scene_yaml(source, opts))
    _add_to_params(params, opts.name)
    log.info("added scene %s: %d photos (%d queries) from %s", opts.name, len(scene.frames), n_query, source)
    return {"name": opts.name, "photos": len(scene.frames), "queries": n_query, "raw": str(raw),
            "config": str(conf), "has_poses": scene.has_poses}


def repro(checkout: Path, name: str) -> int:
    """``dvc repro metrics@<name>``: every stage the scene's metrics need, cached as usual."""
    dvc = shutil.which("dvc")
    if dvc is None:
        raise UsvcError("dvc is not on PATH (pip install -e . installs it)")
    cmd = [dvc, "repro", f"metrics@{name}"]
    log.info("running %s", " ".join(cmd))
    return subprocess.run(cmd, cwd=checkout, check=False).returncode
