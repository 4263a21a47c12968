"""conf/<group>/default.yaml is generated from the group's options dataclass (usvc.pipeline.conf_files):
the files are current, they compose to exactly the dataclass defaults, and values keep their types."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import pytest
import yaml
from conftest import REPO
from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from usvc.pipeline.conf_files import COMMAND, GENERATED, main, render, stale, write, yaml_value

CONF = REPO / "conf"


def test_every_default_yaml_is_generated_and_current(capsys):
    """`--check`: the default.yaml files are what their dataclasses give (run `--write` after
    changing a default or a field's comment)."""
    assert set(GENERATED) == {p.parent.name for p in CONF.glob("*/default.yaml")}
    assert stale() == [], f"stale: run `{COMMAND}`"
    assert main(["--check"]) == 0
    assert capsys.readouterr().out == ""


def test_check_names_a_stale_file_and_write_fixes_it(tmp_path):
    assert [p.parent.name for p in stale(tmp_path)] == list(GENERATED)  # missing files are stale
    write(tmp_path)
    assert stale(tmp_path) == []
    train = tmp_path / "train" / "default.yaml"
    train.write_text(train.read_text().replace("\nlr: 0.005 ", "\nlr: 0.004 "))
    assert stale(tmp_path) == [train]
    assert write(tmp_path) == [train] and stale(tmp_path) == []
    assert yaml.safe_load(train.read_text())["lr"] == 0.005


def _typed(value):
    """A value with its type, lists and tuples alike (a YAML flow list reads back as a list)."""
    if isinstance(value, (list, tuple)):
        return ("list", [_typed(v) for v in value])
    return (type(value).__name__, value)


@pytest.mark.parametrize("group", sorted(GENERATED))
def test_generated_file_loads_to_exactly_the_dataclass_defaults(group):
    """Read as DVC reads it (PyYAML), as Hydra reads it (OmegaConf) and composed with the group's
    schema: the same values, of the same types, in field order."""
    cls = GENERATED[group]
    defaults = dataclasses.asdict(cls())
    path = CONF / group / "default.yaml"
    for loaded in (yaml.safe_load(path.read_text()), OmegaConf.to_container(OmegaConf.load(path))):
        assert loaded.pop("defaults") == [f"base_{group}", "_self_"]
        assert list(loaded) == list(defaults)
        assert {k: _typed(v) for k, v in loaded.items()} == {k: _typed(v) for k, v in defaults.items()}

    ConfigStore.instance().store(group=group, name=f"base_{group}", node=cls)
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(overrides=[f"+{group}=default"])
    assert OmegaConf.to_container(cfg[group]) == defaults
    assert OmegaConf.to_object(cfg[group]) == cls()


@pytest.mark.parametrize("value, text", [
    (50.0, "50.0"), (0.005, "0.005"), (2e-4, "2.0e-4"), (1.6e-6, "1.6e-6"), (1e16, "1.0e+16"), (-0.0, "-0.0"),
    (0, "0"), (-1, "-1"), (None, "null"), (True, "true"), (False, "false"),
    ("auto", "auto"), ("no", '"no"'), ("1.5", '"1.5"'), ("null", '"null"'), ("", '""'), ("a: b", '"a: b"'),
    ([96.0, 24.0, 8.0], "[96.0, 24.0, 8.0]"), ((1, 2.0), "[1, 2.0]"),
])
def test_values_round_trip_with_their_types(value, text):
    """A float stays a float (50.0, not 50; 2.0e-4, which YAML 1.1 reads as a number where 2e-4 is a
    string), strings that YAML would read as something else are quoted."""
    assert yaml_value(value) == text
    for loaded in (yaml.safe_load(f"k: {text}")["k"], OmegaConf.to_container(OmegaConf.create(f"k: {text}"))["k"]):
        assert _typed(loaded) == _typed(value)


def test_shortest_float_text_reads_back_exactly():
    values = [0.1 + 0.2, 1 / 3, 6.02214076e23, 5e-324, 1.7976931348623157e308, 123456789.123, 0.6667, 1.25e-4]
    for value in values:
        for loaded in (yaml.safe_load(yaml_value(value)), OmegaConf.create(f"k: {yaml_value(value)}")["k"]):
            assert isinstance(loaded, float) and loaded == value, (value, yaml_value(value))


@dataclass
class _Example:
    """An example group: its first paragraph
    heads the file.

    Later paragraphs do not."""

    rate: float = 50.0  # the rate, per second
    # a comment block above the field
    name: str = "auto"
    limit: Optional[int] = None
    sizes: list[float] = field(default_factory=lambda: [1.0, 2.5])  # search radii
    on: bool = False


def test_render_layout():
    assert render("example", _Example) == (
        "# An example group: its first paragraph heads the file.\n"
        f"# Generated from tests/test_conf_files.py by `{COMMAND}`: change a default in the dataclass.\n"
        "defaults:\n"
        "  - base_example\n"
        "  - _self_\n"
        "rate: 50.0         # the rate, per second\n"
        "name: auto         # a comment block above the field\n"
        "limit: null\n"
        "sizes: [1.0, 2.5]  # search radii\n"
        "on: false\n"
    )


def test_a_dataclass_without_docstring_is_refused():
    @dataclass
    class Bare:
        x: int = 1

    with pytest.raises(ValueError, match="needs a docstring"):
        render("bare", Bare)


@pytest.mark.parametrize("path", sorted(p for group in ("model", "train") for p in (CONF / group).glob("*.yaml")
                                       if p.name != "default.yaml"), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_alternatives_set_only_what_differs(path):
    """model=small, small_real, xfeat and train=full: every value they set (but the name) differs from the default,
    so the dataclass stays the one place of every default. (The stages that read the model group
    register its schema, which fills in the rest; gaussians=reference stays complete because the
    render stage reads gaussians.tile without registering that group.)"""
    defaults = dataclasses.asdict(GENERATED[path.parent.name]())
    values = yaml.safe_load(path.read_text())
    repeated = [k for k, v in values.items() if k not in ("defaults", "name") and _typed(v) == _typed(defaults[k])]
    assert repeated == [], f"{path} repeats defaults: {repeated}"
