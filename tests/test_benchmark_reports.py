"""Every benchmark leaves its figures in results/benchmarks/<name>.json, through benchmarks/_report.py,
under one naming rule: <family>_<subcommand>[_<scene>][_<variant>]."""

from __future__ import annotations

import ast
import json
import os
import re
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest

from benchmarks import _cli
from benchmarks import _report as report

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"


def test_writes_valid_json_with_command_and_context(tmp_path):
    result = {"scene": "mini", "seconds": 1.5, "rows": [{"a": 1}], "n": np.int64(3), "v": np.float32(0.5)}
    out = report.write_report("demo_mini", result,
                              argv=["/x/benchmarks/demo/__main__.py", "speed", "--scene", "mini", "a b"],
                              directory=tmp_path / "nested")
    assert out == tmp_path / "nested" / "demo_mini.json"
    text = out.read_text()
    data = json.loads(text)
    assert data["command"] == "python -m benchmarks.demo speed --scene mini 'a b'"
    assert list(data) == ["command", "scene", "seconds", "rows", "n", "v", "context"]  # the order the script gave
    assert data["n"] == 3 and data["v"] == 0.5 and data["rows"] == [{"a": 1}]
    ctx = data["context"]
    assert {"torch", "torch_threads", "cpu_count", "cpus_available", "OMP_NUM_THREADS"} <= set(ctx)
    assert isinstance(ctx["torch_threads"], int) and ctx["cpu_count"] >= 1
    assert text.startswith('{\n "command"')  # indent=1
    assert [p.name for p in out.parent.iterdir()] == ["demo_mini.json"]  # no temporary left behind


def test_a_scripts_own_copy_goes_into_a_folder_made_for_it(tmp_path):
    out = tmp_path / "not" / "yet" / "there.json"
    report.write_out(out, '{"a": 1}\n')
    assert json.loads(out.read_text()) == {"a": 1}
    report.write_out(out, '{"a": 2}\n')  # an existing folder and file: replaced
    assert json.loads(out.read_text()) == {"a": 2}


def test_default_directory_is_results_benchmarks():
    assert report.REPORT_DIR == REPO / "results" / "benchmarks"


def test_replaces_an_existing_report(tmp_path):
    report.write_report("demo", {"x": 1}, argv=["demo.py"], directory=tmp_path)
    report.write_report("demo", {"x": 2}, argv=["demo.py"], directory=tmp_path)
    assert json.loads((tmp_path / "demo.json").read_text())["x"] == 2
    assert [p.name for p in tmp_path.iterdir()] == ["demo.json"]


def test_unserialisable_result_writes_nothing(tmp_path):
    report.write_report("demo", {"x": 1}, argv=["demo.py"], directory=tmp_path)
    with pytest.raises(TypeError):
        report.write_report("demo", {"x": object()}, argv=["demo.py"], directory=tmp_path)
    with pytest.raises(TypeError):
        report.write_report("other", {"x": object()}, argv=["demo.py"], directory=tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["demo.json"]
    assert json.loads((tmp_path / "demo.json").read_text())["x"] == 1  # the previous report is intact


def test_failure_while_writing_leaves_no_partial_file(tmp_path, monkeypatch):
    report.write_report("demo", {"x": 1}, argv=["demo.py"], directory=tmp_path)

    def fail(src, dst):
        assert Path(src).read_text()  # the whole text was in the temporary file
        raise OSError("disk went away")

    monkeypatch.setattr(report.os, "replace", fail)
    with pytest.raises(OSError, match="disk went away"):
        report.write_report("demo", {"x": 2}, argv=["demo.py"], directory=tmp_path)
    with pytest.raises(OSError):
        report.write_report("fresh", {"x": 2}, argv=["demo.py"], directory=tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["demo.json"]
    assert json.loads((tmp_path / "demo.json").read_text())["x"] == 1


def test_interrupted_write_leaves_no_partial_file(tmp_path, monkeypatch):
    real_fdopen = os.fdopen

    class Interrupted(BaseException):
        pass

    def fdopen(fd, *args, **kwargs):
        fh = real_fdopen(fd, *args, **kwargs)

        def write(text):
            real_write(text[: len(text) // 2])
            raise Interrupted

        real_write = fh.write
        fh.write = write
        return fh

    monkeypatch.setattr(report.os, "fdopen", fdopen)
    with pytest.raises(Interrupted):
        report.write_report("demo", {"x": list(range(100))}, argv=["demo.py"], directory=tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("field", ["command", "context"])
def test_reserved_fields_are_refused(tmp_path, field):
    with pytest.raises(ValueError, match=field):
        report.write_report("demo", {field: 1}, argv=["demo.py"], directory=tmp_path)


@pytest.mark.parametrize("name", ["", "../escape", "a/b", "with space", ".hidden"])
def test_bad_names_are_refused(tmp_path, name):
    with pytest.raises(ValueError):
        report.write_report(name, {"x": 1}, argv=["demo.py"], directory=tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_one_naming_rule_family_subcommand_scene_variants():
    args = Namespace(family="query", subcommand="before-after", variant=None)
    assert report.report_name(args) == "query_before_after"
    args = Namespace(family="query", subcommand="speed", variant="poselib")
    assert report.report_name(args, "mini", "640x480", None, "") == "query_speed_mini_640x480_poselib"
    assert report.report_name(Namespace(family="pipeline", subcommand="scaling"), None, 3) == "pipeline_scaling_3"


def test_scene_of():
    assert report.scene_of(Path("data/mini/buffer/buffer.h5"), "buffer") == "mini"
    assert report.scene_of(Path("data/office_photos/prepared"), "prepared") == "office_photos"
    assert report.scene_of(Path("data/office/"), None) == "office"
    assert report.scene_of(Path("/elsewhere/b.h5"), "buffer") == "b"


# --- every benchmark writes a report -----------------------------------------------------------

SCRIPTS = sorted(BENCHMARKS / family / f"{module}.py" for family in _cli.FAMILIES
                 for module, _ in _cli.family_package(family).SUBCOMMANDS.values())


def _docstrings(tree: ast.Module) -> set[int]:
    """ids of the docstring nodes (module, classes, functions): mentions there write nothing."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def writes_report(source: str) -> bool:
    """A call to write_report, or code (not a docstring) naming results/benchmarks as a path."""
    tree = ast.parse(source)
    docs = _docstrings(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None
            if name == "write_report":
                return True
        if (isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs
                and "results/benchmarks" in node.value):
            return True
        if (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)
                and isinstance(node.right, ast.Constant) and node.right.value == "benchmarks"
                and isinstance(node.left, ast.BinOp) and isinstance(node.left.right, ast.Constant)
                and node.left.right.value == "results"):
            return True
    return False


def names_outside_the_rule(source: str) -> list[str]:
    """The write_report calls whose name is not `report_name(...)` (the one naming rule), as source."""
    tree = ast.parse(source)
    calls = [node for node in ast.walk(tree) if isinstance(node, ast.Call)
             and getattr(node.func, "id", getattr(node.func, "attr", None)) == "write_report"]
    names = {node.targets[0].id: node.value for node in ast.walk(tree)  # name = report_name(...); write_report(name)
             if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)}
    out = []
    for call in calls:
        arg = call.args[0] if call.args else None
        arg = names.get(arg.id, arg) if isinstance(arg, ast.Name) else arg
        if not (isinstance(arg, ast.Call) and getattr(arg.func, "id", None) == "report_name"):
            out.append(ast.unparse(call.args[0]) if call.args else "(none)")
    return out


def test_the_static_check_catches_a_benchmark_that_forgets():
    assert not writes_report('"""Prints; writes results/benchmarks/x.json (says the docstring)."""\nprint(1)\n')
    assert not writes_report("def main():\n    print({'a': 1})\n")
    assert writes_report("from _report import write_report\nwrite_report('x', {})\n")
    assert writes_report("import _report\n_report.write_report('x', {})\n")
    assert writes_report("out = ROOT / 'results' / 'benchmarks' / 'x.json'\n")
    assert writes_report("out = 'results/benchmarks/x.json'\n")


def test_the_static_check_catches_a_name_outside_the_rule():
    assert names_outside_the_rule("write_report('x_y', {})\n") == ["'x_y'"]
    assert names_outside_the_rule("n = f'x_{a}'\nwrite_report(n, {})\n") == ["n"]
    assert not names_outside_the_rule("n = report_name(args, s)\nwrite_report(n, {})\n")
    assert not names_outside_the_rule("print(write_report(report_name(args), {}))\n")


def test_there_are_benchmarks():
    assert len(SCRIPTS) >= 20 and all(s.is_file() for s in SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_benchmark_writes_a_report(script):
    source = script.read_text()
    assert writes_report(source), (f"{script.name} does not write results/benchmarks/<name>.json: "
                                   "build a dict of its figures and call _report.write_report")
    assert not names_outside_the_rule(source), "name reports with _report.report_name (one naming rule)"
    doc = ast.get_docstring(ast.parse(source)) or ""
    family = script.parent.name
    assert f"results/benchmarks/{family}_" in doc, f"{script.name}'s docstring does not say where its JSON goes"
    assert f"python -m benchmarks.{family} " in doc, f"{script.name}'s docstring does not say how to run it"


KNOWN = {f"{family}_{name.replace('-', '_')}" for family in _cli.FAMILIES
         for name in _cli.family_package(family).SUBCOMMANDS}


def test_every_committed_report_is_named_by_the_rule():
    """results/benchmarks/<family>_<subcommand>[_<scene>][_<variant>].json: a committed report starts
    with the family and subcommand that write it."""
    names = [p.stem for p in sorted((REPO / "results" / "benchmarks").glob("*.json"))]
    assert names and all(re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", n) for n in names)
    assert [n for n in names if not any(n == k or n.startswith(k + "_") for k in KNOWN)] == []
