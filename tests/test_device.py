"""One `device` setting for every stage that runs torch, `usvc localize --device` and the API:
checked at config time, resolved once, a CUDA device that is not there is one clear line."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import REPO

from usvc.core import device as dev
from usvc.core.errors import UsvcError
from usvc.pipeline.config import ConfigError, compose_for_script


@pytest.mark.parametrize("setting", ["auto", "cpu", "cuda", "cuda:0", "cuda:12"])
def test_device_settings_are_recognised(setting):
    assert dev.device_problem(setting) == ""


@pytest.mark.parametrize("setting", ["gpu", "CUDA", "cuda:", "cuda:x", "mps", "", None, 0])
def test_other_device_settings_are_refused_naming_the_choices(setting):
    assert "is not one of auto | cpu | cuda | cuda:N" in dev.device_problem(setting)


def test_auto_is_cuda_only_where_torch_sees_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert dev.resolve_device("auto") == "cpu" and dev.resolve_device("cpu") == "cpu"
    with pytest.raises(UsvcError, match=r"device='cuda': CUDA is not available to this torch build or machine"):
        dev.resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert dev.resolve_device("auto") == "cuda" and dev.resolve_device("cuda:1") == "cuda:1"
    with pytest.raises(UsvcError, match=r"device='cuda:2': this machine has 2 CUDA device\(s\), cuda:0 to cuda:1"):
        dev.resolve_device("cuda:2")


def test_the_cpu_is_named():
    record = dev.device_record("cpu")
    assert record["device"] == "cpu" and record["device_name"]


def test_a_bad_device_fails_at_config_time_naming_the_key():
    with pytest.raises(ConfigError, match=r"config key device='gpu' is not one of auto \| cpu \| cuda \| cuda:N"):
        compose_for_script("mini", ["device=gpu"])
    assert compose_for_script("mini", ["device=cpu"]).device == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("stage", ["buffer", "train", "relocalize", "gaussians", "render"])
def test_cuda_where_there_is_none_stops_a_torch_stage_in_one_line(stage, tmp_path):
    proc = subprocess.run([sys.executable, "-m", f"stages.{stage}", "device=cuda", f"data_dir={tmp_path / 'd'}",
                           f"results_dir={tmp_path / 'r'}", f"hydra.run.dir={tmp_path / 'log'}"],
                          cwd=REPO, capture_output=True, text=True)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "Traceback" not in out, out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "device='cuda': CUDA is not available" in errors[0], out
    assert not (tmp_path / "d").exists() and not (tmp_path / "r").exists()


def test_the_torch_stages_and_only_they_resolve_the_device(monkeypatch):
    import importlib

    from usvc.pipeline.config import register_configs

    monkeypatch.syspath_prepend(str(REPO))
    try:
        for name in ("prepare", "sfm", "keypoints", "landmarks", "metrics", "buffer", "train", "relocalize",
                     "gaussians", "render"):
            stage = importlib.import_module(f"stages.{name}").stage
            assert stage.torch_device == (name in ("buffer", "train", "relocalize", "gaussians", "render")), name
    finally:
        register_configs()  # a stage registers only its own groups' schemas: every group typed again for the others
