"""The code each stage runs, from its imports: what `dvc.yaml` must list as the stage's code deps.

A stage's code is its entry point `stages/<stage>.py` plus every usvc module it imports, directly or
through other modules (function-local imports included, since they run too), plus the
`__init__.py` of every package on the way. A package folder is listed whole when the stage uses
all of its modules (e.g. `usvc/model`, `usvc/weights`, whose weight files the stage reads);
otherwise each module it uses is listed.

    python -m usvc.pipeline.code_deps            # print each stage's code deps
    python -m usvc.pipeline.code_deps --check    # exit 1 when dvc.yaml differs (the test does this)
    python -m usvc.pipeline.code_deps --write    # rewrite the code deps in dvc.yaml, data deps kept
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterable
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
CODE_ROOTS = ("usvc", "stages")


def module_file(module: str, root: Path = ROOT) -> Path | None:
    """`usvc.sfm.tracks_file` -> usvc/sfm/tracks_file.py (or the package's __init__.py); None if not ours."""
    if module.split(".")[0] not in CODE_ROOTS:
        return None
    base = root.joinpath(*module.split("."))
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _dynamic_package(node: ast.Call) -> str | None:
    """`importlib.import_module(f"usvc.pkg.{name}")` -> "usvc.pkg": the call may load any of its modules."""
    func = node.func
    if not (isinstance(func, ast.Attribute) and func.attr == "import_module" and node.args):
        return None
    arg = node.args[0]
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        prefix = str(arg.values[0].value)
        if prefix.endswith("."):
            return prefix[:-1]
    return None


def imported_modules(path: Path, root: Path = ROOT) -> set[str]:
    """Every module an import statement anywhere in the file names (`from a.b import c` names a.b,
    and a.b.c when c is a submodule); an `importlib.import_module(f"pkg.{...}")` names every
    module of pkg."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Call) and (package := _dynamic_package(node)) is not None:
            folder = root.joinpath(*package.split("."))
            found.update(f"{package}.{p.stem}" for p in folder.glob("*.py") if p.stem != "__init__")
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the modules of ours it imports (explicit imports only, not parent packages)."""
    graph: dict[str, set[str]] = {}
    for top in CODE_ROOTS:
        for path in sorted((root / top).rglob("*.py")):
            name = module_name(path, root)
            graph[name] = {m for m in imported_modules(path, root) if module_file(m, root) is not None} - {name}
    return graph


def closure(module: str, root: Path = ROOT) -> set[Path]:
    """Files that run when `module` is imported: its imports, transitively, and the __init__.py of
    every package on the way (their own imports are followed only where a module imports the
    package itself)."""
    files: set[Path] = set()
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = module_file(name, root)
        if path is None:
            continue
        files.add(path)
        parts = name.split(".")
        for i in range(1, len(parts)):
            parent = module_file(".".join(parts[:i]), root)
            if parent is not None:
                files.add(parent)
        todo.extend(m for m in imported_modules(path, root) if module_file(m, root) is not None)
    return files


def _package_files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts}


def compress(files: set[Path], root: Path = ROOT) -> list[str]:
    """Whole package folders where every file in them is used (data files count as used when the
    package is: `usvc/weights` ships the encoders), single files elsewhere."""
    used = set(files)
    out: set[str] = set()
    folders = sorted({p.parent for p in files if p.name == "__init__.py" and p.parent != root / "usvc"},
                     key=lambda f: len(f.parts))
    covered: set[Path] = set()
    for folder in folders:
        if any(folder.is_relative_to(c) for c in covered):
            continue
        py = {p for p in _package_files(folder) if p.suffix == ".py"}
        if py <= used:
            out.add(folder.relative_to(root).as_posix())
            covered.add(folder)
    for path in files:
        if not any(path.is_relative_to(c) for c in covered):
            out.add(path.relative_to(root).as_posix())
    return sorted(out)


def stage_code_deps(stage: str, root: Path = ROOT) -> list[str]:
    return compress(closure(f"stages.{stage}", root), root)


def _is_code(dep: str) -> bool:
    return dep.split("/")[0] in CODE_ROOTS


def dvc_code_deps(dvc_yaml: Path = ROOT / "dvc.yaml") -> dict[str, list[str]]:
    """Each stage's code deps as dvc.yaml lists them (foreach stages read from their `do` body)."""
    stages = yaml.safe_load(dvc_yaml.read_text())["stages"]
    out = {}
    for name, body in stages.items():
        body = body.get("do", body)
        out[name] = sorted(d for d in body.get("deps", []) if _is_code(d))
    return out


def differences(dvc_yaml: Path = ROOT / "dvc.yaml", root: Path = ROOT) -> dict[str, tuple[list[str], list[str]]]:
    """Stage -> (code it runs that dvc.yaml does not list, listed code it does not run)."""
    out = {}
    for stage, listed in dvc_code_deps(dvc_yaml).items():
        wanted = stage_code_deps(stage, root)
        missing, extra = sorted(set(wanted) - set(listed)), sorted(set(listed) - set(wanted))
        if missing or extra:
            out[stage] = (missing, extra)
    return out


def rewrite(dvc_yaml: Path = ROOT / "dvc.yaml", root: Path = ROOT) -> None:
    """Replace each stage's code deps in dvc.yaml with its closure; data deps, order and comments
    elsewhere are kept."""
    lines = dvc_yaml.read_text().splitlines(keepends=True)
    out: list[str] = []
    stage = None
    i = 0
    while i < len(lines):
        line = lines[i]
        stripped = line.strip()
        if line.startswith("  ") and not line.startswith("   ") and stripped.endswith(":"):
            stage = stripped[:-1]
        if stripped == "deps:" and stage is not None:
            out.append(line)
            indent = line[: len(line) - len(line.lstrip())] + "  "
            i += 1
            data: list[str] = []
            while i < len(lines) and lines[i].startswith(indent + "- "):
                dep = lines[i].strip()[2:]
                if not _is_code(dep):
                    data.append(lines[i])
                i += 1
            out.extend(f"{indent}- {dep}\n" for dep in stage_code_deps(stage, root))
            out.extend(data)
            continue
        out.append(line)
        i += 1
    dvc_yaml.write_text("".join(out))


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Import cycles (strongly connected components of more than one module, or self-imports)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _print(stages: Iterable[str]) -> None:
    for stage in stages:
        print(f"{stage}:")
        for dep in stage_code_deps(stage):
            print(f"  - {dep}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="exit 1 when dvc.yaml's code deps differ")
    mode.add_argument("--write", action="store_true", help="rewrite dvc.yaml's code deps")
    args = parser.parse_args(argv)
    if args.write:
        rewrite()
        return 0
    if args.check:
        diff = differences()
        for stage, (missing, extra) in diff.items():
            print(f"{stage}: missing {missing or '-'}; not run by the stage {extra or '-'}")
        return 1 if diff else 0
    _print(dvc_code_deps())
    return 0


if __name__ == "__main__":
    sys.exit(main())
