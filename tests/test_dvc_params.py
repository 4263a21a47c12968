"""What DVC tracks for a stage must cover every config value the stage's entry point reads."""

from __future__ import annotations

import re

import pytest
import yaml
from conftest import REPO

from usvc.pipeline.config import GROUP_SCHEMAS

DVC = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]


def _tracked(stage: dict) -> set[str]:
    body = stage.get("do", stage)
    tracked = set()
    for entry in body.get("params", []):
        for path, keys in (entry.items() if isinstance(entry, dict) else [(entry, None)]):
            if path.startswith("conf/scene/"):
                tracked.add("scene")
            elif path == "conf/config.yaml":
                tracked.update(k for k in keys or [] if k != "defaults")
            else:
                tracked.add(path.split("/")[1])
    return tracked


def _read_by(module: str) -> set[str]:
    src = (REPO / "stages" / f"{module}.py").read_text()
    used = {g for g in re.findall(r"cfg\.(\w+)", src)}
    # the scene's name only picks the artifact paths, which dvc.yaml spells per scene
    if not re.search(r"cfg\.scene\.(?!name\b)\w+|=\s*cfg\.scene\b", src):
        used.discard("scene")
    return used - {"data_dir", "results_dir"}


@pytest.mark.parametrize("name", sorted(DVC))
def test_stage_tracks_what_it_reads(name):
    stage = DVC[name]
    module = (stage.get("do", stage))["cmd"].split()[2].split(".")[1]
    read = _read_by(module)
    if not (stage.get("do", stage)).get("params"):
        # a stage without params must not read any config (metrics takes everything from artifacts)
        assert not read, f"stages/{module}.py reads {sorted(read)} but dvc stage {name} tracks no params"
        return
    missing = read - _tracked(stage)
    assert not missing, f"dvc stage {name} does not track {sorted(missing)}, which stages/{module}.py reads"


def test_every_group_is_tracked_somewhere():
    tracked = set().union(*(_tracked(s) for s in DVC.values()))
    assert set(GROUP_SCHEMAS) <= tracked
