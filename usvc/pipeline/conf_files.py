"""`conf/<group>/default.yaml` generated from the group's options dataclass: one place per default.

Each step's options dataclass (e.g. `usvc/train/options.py`) holds the defaults and, in the comment
on each field, what the field means. The group's `default.yaml`, which Hydra composes and DVC
tracks, is written from it: a header (the class docstring's first paragraph), the defaults list,
then every field in field order with its default and its comment. The other option files are
hand-written: the model alternatives (`conf/model/small.yaml`, ...) set only what differs from the
defaults, `conf/method/*.yaml` set the values each method stands for, and the scene files (which
`usvc map` writes) and `conf/gaussians/reference.yaml` set every field (a stage that reads a group
without registering its schema sees only the file's own values).

    python -m usvc.pipeline.conf_files            # print every generated file
    python -m usvc.pipeline.conf_files --check    # exit 1 naming each default.yaml that is stale
    python -m usvc.pipeline.conf_files --write    # rewrite the stale ones
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import sys
import textwrap
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import yaml

from usvc.buffer.options import BufferOptions
from usvc.gaussians.options import GaussiansOptions
from usvc.generate.params import RoomParams
from usvc.keypoints.options import KeypointOptions
from usvc.landmarks.options import LandmarksOptions
from usvc.model.options import ModelOptions
from usvc.pipeline.stage_help import field_docs
from usvc.relocalize.options import RelocalizeOptions
from usvc.render.options import RenderOptions
from usvc.sfm.options import SfmOptions
from usvc.train.options import TrainOptions

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
COMMAND = "python -m usvc.pipeline.conf_files --write"
HEADER_WIDTH = 100

# The groups whose conf/<group>/default.yaml is generated, and the dataclass each is written from
# (the `scene` group has no default: each scene file names its own photos).
GENERATED: dict[str, type] = {
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


def default_value(f: Any) -> Any:
    """A dataclass field's default (a default_factory is called)."""
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    raise ValueError(f"field {f.name} has no default: a default.yaml cannot be written for it")


def _plain_string(text: str) -> bool:
    """Whether `text` can stand unquoted: YAML reads it back as the same string, and OmegaConf
    sees no interpolation in it."""
    if not text or text != text.strip() or "${" in text or any(c in text for c in "#:{}[],&*!|>'\"%@`\n"):
        return False
    try:
        return yaml.safe_load(text) == text
    except yaml.YAMLError:
        return False


def _float(value: float) -> str:
    """The shortest text that reads back as `value`, with a '.' (YAML 1.1, which PyYAML and DVC read,
    takes `1e-4` for a string): 50.0, 0.005, and below 1e-3 in exponent form, 1.6e-4, 2.0e-4."""
    if value != 0 and not 1e-3 <= abs(value) < 1e16:
        text = next(t for t in (f"{value:.{p}e}" for p in range(17)) if float(t) == value)
        mantissa, exponent = text.split("e")
        mantissa += "" if "." in mantissa else ".0"
        return f"{mantissa}e{exponent[0]}{int(exponent[1:])}"
    return repr(value)  # no exponent in this range, always a '.'


def yaml_value(value: Any) -> str:
    """`value` as YAML that loads (PyYAML and Hydra alike) to an equal value of the same type:
    floats keep a '.' (50.0, 2.0e-4), None is null, bools are lower-case, strings are quoted only
    when needed, tuples and lists are flow lists."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return ".nan"
        if math.isinf(value):
            return ".inf" if value > 0 else "-.inf"
        return _float(value)
    if isinstance(value, str):
        return value if _plain_string(value) else json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    raise TypeError(f"no YAML form for a default of type {type(value).__name__}: {value!r}")


def summary(cls: type) -> str:
    """The first paragraph of the class docstring, on one line."""
    doc = inspect.getdoc(cls) or ""
    if not doc or doc.startswith(f"{cls.__name__}("):  # a dataclass without a docstring gets its signature
        raise ValueError(f"{cls.__name__} needs a docstring: its first paragraph heads the generated default.yaml")
    return " ".join(doc.split("\n\n")[0].split())


def source_file(cls: type) -> str:
    return Path(inspect.getfile(cls)).resolve().relative_to(ROOT).as_posix()


def render(group: str, cls: type) -> str:
    """The text of conf/<group>/default.yaml written from `cls`."""
    head = textwrap.wrap(summary(cls), HEADER_WIDTH - 2, break_long_words=False, break_on_hyphens=False)
    head.append(f"Generated from {source_file(cls)} by `{COMMAND}`: change a default in the dataclass.")
    docs = field_docs(cls)
    body = [(f"{f.name}: {yaml_value(default_value(f))}", docs.get(f.name, "")) for f in fields(cls)]
    column = max((len(line) for line, doc in body if doc), default=0) + 2
    lines = [f"# {text}" for text in head]
    lines += ["defaults:", f"  - base_{group}", "  - _self_"]
    lines += [f"{line.ljust(column)}# {doc}" if doc else line for line, doc in body]
    return "\n".join(lines) + "\n"


def default_path(group: str, conf: Path = CONF) -> Path:
    return conf / group / "default.yaml"


def stale(conf: Path = CONF) -> list[Path]:
    """The generated files whose text is not what their dataclass gives (or that are missing)."""
    out = []
    for group, cls in GENERATED.items():
        path = default_path(group, conf)
        if not path.is_file() or path.read_text() != render(group, cls):
            out.append(path)
    return out


def write(conf: Path = CONF) -> list[Path]:
    """Rewrite the stale generated files; returns them."""
    changed = stale(conf)
    for path in changed:
        group = path.parent.name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(render(group, GENERATED[group]))
    return changed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="exit 1 when a default.yaml differs from its dataclass")
    mode.add_argument("--write", action="store_true", help="rewrite the default.yaml files that differ")
    args = parser.parse_args(argv)
    if args.write:
        for path in write():
            print(f"wrote {path.relative_to(ROOT)}")
        return 0
    if args.check:
        paths = stale()
        for path in paths:
            print(f"{path.relative_to(ROOT)} is stale: run `{COMMAND}`")
        return 1 if paths else 0
    for group, cls in GENERATED.items():
        print(f"--- conf/{group}/default.yaml")
        print(render(group, cls), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
