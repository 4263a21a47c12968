"""`python -m stages.<stage> --help` shows the options the stage reads with their meaning, from the
options dataclasses (the one schema), and every option is documented."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest

from usvc.pipeline.config import Config, group_schemas
from usvc.pipeline.stage_help import field_docs, groups_read, stage_help

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("schema", [Config, *group_schemas().values()], ids=lambda s: s.__name__)
def test_every_option_has_a_one_line_meaning(schema):
    docs = field_docs(schema)
    undocumented = [f.name for f in fields(schema) if not docs.get(f.name)]
    assert not undocumented, f"{schema.__name__}: no comment on {undocumented}"


def test_train_help_lists_its_groups_with_values_and_meanings():
    out = subprocess.run([sys.executable, "-m", "stages.train", "--help", "train.lr=0.01"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    assert "train.lr=0.01  # peak learning rate" in out  # the override's value, the field's comment
    assert "model.head_width=256" in out  # model=small, the configured default
    assert "train (TrainOptions, usvc/train/options.py; train=<default|full|long>)" in out  # the alternatives too
    assert "relocalize.max_error_px" not in out  # train does not read the relocalize group
    assert "base_" not in out


def test_the_groups_shown_are_the_ones_dvc_tracks():
    assert groups_read("relocalize") == ["scene", "model", "relocalize"]
    assert groups_read("sfm") == ["scene", "sfm"]
    assert "buffer.holdout_every=0" in stage_help("buffer")
