"""The code layout follows the pipeline: a package per stage, no import cycles, and dvc.yaml lists
exactly the code each stage runs (so editing a module reruns exactly the stages that import it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

from usvc.pipeline import code_deps

ROOT = Path(__file__).resolve().parents[1]
STAGES = list(yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"])


def test_every_stage_has_its_package_and_runs_it():
    for stage in STAGES:
        package = ROOT / "usvc" / stage
        assert (package / "__init__.py").is_file(), f"no package usvc/{stage} for stage {stage}"
        deps = code_deps.stage_code_deps(stage)
        assert any(d == f"usvc/{stage}" or d.startswith(f"usvc/{stage}/") for d in deps), (stage, deps)


def test_dvc_yaml_lists_the_code_each_stage_runs():
    diff = code_deps.differences()
    expected = {s: code_deps.stage_code_deps(s) for s in diff}
    assert diff == {}, (
        "dvc.yaml's code deps differ from the stages' imports (run `python -m usvc.pipeline.code_deps --write`):\n"
        + "\n".join(f"{s}: missing {m}, not run {e}\n  expected {expected[s]}" for s, (m, e) in diff.items()))


def test_a_dep_missing_from_dvc_yaml_is_reported(tmp_path):
    correct = tmp_path / "correct.yaml"
    correct.write_text((ROOT / "dvc.yaml").read_text())
    code_deps.rewrite(correct)
    assert code_deps.differences(correct) == {}
    text = correct.read_text()
    assert "        - usvc/sfm/tracks_file.py\n" in text
    broken = tmp_path / "dvc.yaml"
    # Drop tracks.py from every stage that lists it, and add a module that no stage imports.
    broken.write_text(text.replace("        - usvc/sfm/tracks_file.py\n", "").replace(
        "        - stages/relocalize.py\n", "        - stages/relocalize.py\n        - usvc/gaussians/fit.py\n"))
    diff = code_deps.differences(broken)
    assert diff["train"][0] == ["usvc/sfm/tracks_file.py"]
    assert diff["keypoints"][0] == ["usvc/sfm/tracks_file.py"]
    assert diff["relocalize"] == ([], ["usvc/gaussians/fit.py"])


def test_function_local_and_dynamic_imports_count():
    # the config imports the thread policy inside a function; prepare loads its format importers by name.
    assert ROOT / "usvc/pipeline/threads.py" in code_deps.closure("usvc.pipeline.config")
    prepare = code_deps.closure("usvc.prepare.importers")
    assert ROOT / "usvc/prepare/importers/cambridge.py" in prepare


def test_no_import_cycles():
    assert code_deps.cycles(code_deps.import_graph()) == []


def test_cycles_are_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert code_deps.cycles(graph) == [["a", "b", "c"]]


def test_the_config_module_loads_no_step():
    """The config names each group's schema; importing it loads no step's code (a stage imports the
    options it reads), and neither torch nor OpenCV."""
    code = ("import sys; import usvc.pipeline.config; "
            "print(sorted(m for m in sys.modules if m.startswith(('usvc.', 'torch', 'cv2')) "
            "and not m.startswith(('usvc.pipeline', 'usvc.core')) and m != 'usvc.'))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# The packages in layers: a module imports only from its own package or a lower layer, so no import
# runs back up (a step never reaches the pipeline shell above it, a stage's inputs never reach a
# later stage's code).
LAYERS: tuple[frozenset[str], ...] = tuple(frozenset(layer.split()) for layer in (
    "core",
    "generate splat model sfm",
    "weights prepare keypoints landmarks gaussians",
    "render",
    "buffer",
    "train relocalize",
    "metrics analysis pretrain",
    "pipeline",
    "serve",
    "cli client",
))


def _layer(package: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if package in layer)


def test_every_package_has_a_layer():
    packages = {p.name for p in (ROOT / "usvc").iterdir() if (p / "__init__.py").is_file()} | {"cli"} \
        | {p.stem for p in (ROOT / "usvc").glob("*.py") if p.stem != "__init__"}  # a module of its own: usvc.client
    assert packages == set().union(*LAYERS)


def test_no_import_runs_back_up_a_layer():
    upward = []
    for module, imported in code_deps.import_graph().items():
        if not module.startswith("usvc."):
            continue
        here = module.split(".")[1]
        for other in imported:
            if other.count(".") == 0:  # `import usvc` (the package's own __init__)
                continue
            there = other.split(".")[1]
            if there != here and _layer(there) >= _layer(here):
                upward.append(f"{module} imports {other}")
    assert upward == []
