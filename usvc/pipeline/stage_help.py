"""`python -m stages.<stage> --help`: the options the stage reads, each with its default and meaning.

The meaning is the comment on the field's line in the step's options dataclass (or the comment
block just above it): the dataclass is the one schema, so the help cannot drift from it. The
groups shown are the ones the stage registers (`usvc.pipeline.stage.Stage`), the same ones its
dvc.yaml params track. Hydra's own help stays available as `--hydra-help`.
"""

from __future__ import annotations

import ast
import inspect
import io
import tokenize
from dataclasses import MISSING, fields
from pathlib import Path

import yaml

from usvc.pipeline.config import GROUPS, TOP_LEVEL, Config, group_schemas

ROOT = Path(__file__).resolve().parents[2]


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the comment documenting it in the class's source."""
    source = inspect.getsource(cls)
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    lines = source.splitlines()
    docs: dict[str, str] = {}
    for node in ast.parse(source).body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            line = node.lineno
            text = comments.get(line, "")
            if not text:  # a comment block just above the field
                above = []
                k = line - 1
                while k >= 1 and lines[k - 1].strip().startswith("#"):
                    above.insert(0, comments.get(k, ""))
                    k -= 1
                text = " ".join(above)
            docs[node.target.id] = text
    return docs


def _default(f) -> str:
    if f.default is not MISSING:
        return "null" if f.default is None else str(f.default).lower() if isinstance(f.default, bool) else str(f.default)
    return "(a group)"


def groups_read(stage: str, dvc_yaml: Path = ROOT / "dvc.yaml") -> list[str]:
    """Config groups whose files the stage's dvc.yaml params track, in schema order."""
    body = yaml.safe_load(dvc_yaml.read_text())["stages"][stage]
    body = body.get("do", body)
    tracked = set()
    for entry in body.get("params", []):
        path = next(iter(entry)) if isinstance(entry, dict) else entry
        parts = Path(str(path)).parts
        if len(parts) >= 3 and parts[0] == "conf":
            tracked.add(parts[1].replace("${item}", "scene"))
    tracked.add("scene")
    return [g for g in GROUPS if g in tracked]


def choices(group: str, conf: Path = ROOT / "conf") -> list[str]:
    return sorted(p.stem for p in (conf / group).glob("*.yaml"))


def _composed(overrides: list[str]):
    """The config this command line would run with, or None when it does not compose."""
    from hydra import compose, initialize_config_dir

    from usvc.pipeline.config import register_configs

    register_configs()
    try:
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
            return compose(config_name="config", overrides=overrides)
    except Exception:  # noqa: BLE001  (the run itself reports what is wrong with the overrides)
        return None


def _value(cfg, group: str | None, f) -> str:
    if cfg is None:
        return _default(f)
    node = cfg if group is None else cfg[group]
    value = node[f.name]
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def stage_help(stage: str, overrides: list[str] | None = None, schemas: dict[str, type] | None = None) -> str:
    """The help text: every option the stage reads (`schemas`: the groups it registers; default: the
    groups its dvc.yaml params track), with the value this command line would use."""
    cfg = _composed(list(overrides or []))
    out = [f"python -m stages.{stage} scene=<name> [key=value ...]", "",
           f"Runs the {stage} stage on one scene (dvc repro runs it for every scene in params.yaml).",
           "Options it reads, with the values this command line gives them (conf/ plus overrides):", ""]
    top = {f.name: f for f in fields(Config)}
    top_docs = field_docs(Config)
    for name in TOP_LEVEL:
        out.append(f"  {name}={_value(cfg, None, top[name])}  # {top_docs.get(name, '')}")
    out.append(f"  method: one of {', '.join(choices('method'))} (sets train.bundle_weight, relocalize.refine, "
               "buffer.rendered_views)")
    schemas = group_schemas(groups_read(stage)) if schemas is None else schemas
    for group, schema in schemas.items():
        module = inspect.getmodule(schema)
        where = Path(inspect.getfile(schema)).relative_to(ROOT).as_posix() if module else "?"
        options = choices(group)
        pick = f"; {group}=<{'|'.join(o for o in options if not o.startswith('base_'))}>" if len(options) > 1 else ""
        out += ["", f"{group} ({schema.__name__}, {where}{pick}):"]
        docs = field_docs(schema)
        for f in fields(schema):
            out.append(f"  {group}.{f.name}={_value(cfg, group, f)}  # {docs.get(f.name, '')}")
    out += ["", "Hydra's own options (multirun, config paths, logging): --hydra-help"]
    return "\n".join(out)
