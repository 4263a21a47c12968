"""`usvc map`: a folder of photos becomes a scene of the checkout in one command."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from conftest import REPO
from hydra import compose, initialize_config_dir
from test_exif import photo

from usvc import cli
from usvc.core.errors import UsvcError
from usvc.pipeline.config import register_configs, validate
from usvc.prepare.new_scene import NewSceneOptions, add_scene, find_checkout

register_configs()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    shutil.copytree(REPO / "conf", root / "conf")
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, root / name)
    return root


@pytest.fixture
def photos(tmp_path: Path) -> Path:
    folder = tmp_path / "capture"
    folder.mkdir()
    for i in range(9):
        photo(folder / f"IMG_{i:04d}.jpg", size=(80, 60), **{"a405": 26})
    return folder


def test_map_adds_photos_config_and_params_entry(checkout: Path, photos: Path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(checkout / "conf")  # any folder inside the checkout
    calls = []
    monkeypatch.setattr("usvc.prepare.new_scene.subprocess.run",
                        lambda cmd, cwd, check: calls.append((cmd, cwd)) or type("R", (), {"returncode": 0})())
    monkeypatch.setattr("usvc.prepare.new_scene.shutil.which", lambda name: f"/bin/{name}")
    assert cli.main(["map", str(photos), "--name", "kitchen"]) == 0
    assert calls == [(["/bin/dvc", "repro", "metrics@kitchen"], checkout)]
    assert '"photos": 9' in capsys.readouterr().out
    assert sorted(p.name for p in (checkout / "data/raw/kitchen").iterdir()) == sorted(p.name for p in photos.iterdir())
    params = (checkout / "params.yaml").read_text()
    assert yaml.safe_load(params)["scenes"] == ["mini", "kitchen"]
    assert params.startswith((REPO / "params.yaml").read_text().split("scenes:")[0])  # comments kept
    scene = yaml.safe_load((checkout / "conf/scene/kitchen.yaml").read_text())
    mini = yaml.safe_load((REPO / "conf/scene/mini.yaml").read_text())
    assert set(scene) == set(mini)
    with initialize_config_dir(config_dir=str(checkout / "conf"), version_base=None):
        validate(compose("config", overrides=["scene=kitchen"]))
    assert scene | {"defaults": None} == {"defaults": None, "name": "kitchen", "format": "images",
                                          "path": "data/raw/kitchen", "split": "every_nth", "split_n": 8,
                                          "metric_scale": None, "working_width": 640, "undistort_fov": "crop",
                                          "generated": False, "exif_focal": True}


@pytest.mark.parametrize("name, fmt, message", [
    ("Kitchen", "images", "use lower-case letters"),
    ("mini", "images", r"scene 'mini' already exists \(.*mini.yaml\)"),
    ("kitchen", "jpeg", "format 'jpeg' is not one of"),
    ("kitchen", "llff", "poses_bounds.npy"),
])
def test_bad_requests_fail_before_anything_is_written(checkout: Path, photos: Path, name, fmt, message) -> None:
    before = (checkout / "params.yaml").read_text(), sorted((checkout / "conf/scene").iterdir())
    with pytest.raises(UsvcError, match=message):
        add_scene(photos, checkout, NewSceneOptions(name, fmt))
    assert ((checkout / "params.yaml").read_text(), sorted((checkout / "conf/scene").iterdir())) == before
    assert not (checkout / "data").exists()


def test_outside_a_checkout_is_one_line(tmp_path: Path, photos: Path, monkeypatch, capsys) -> None:
    with pytest.raises(UsvcError, match="is not inside a usvc checkout"):
        find_checkout(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["map", str(photos), "--name", "kitchen", "--no-run"]) == 1
    assert capsys.readouterr().err.count("\n") == 1


def test_a_second_scene_with_the_same_name_is_refused(checkout: Path, photos: Path) -> None:
    add_scene(photos, checkout, NewSceneOptions("kitchen"))
    with pytest.raises(UsvcError, match="scene 'kitchen' already exists"):
        add_scene(photos, checkout, NewSceneOptions("kitchen"))
    assert yaml.safe_load((checkout / "params.yaml").read_text())["scenes"] == ["mini", "kitchen"]
