"""`usvc map` against bad input: every refusal is one line before anything is written, and a scene
is either fully registered (photos, config, params entry) or not at all, whatever fails or interrupts."""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from conftest import REPO
from hydra import compose, initialize_config_dir
from test_exif import photo

from usvc import cli
from usvc.core.errors import UsvcError
from usvc.pipeline.config import register_configs, validate
from usvc.prepare import new_scene
from usvc.prepare.importers import load_scene
from usvc.prepare.importers.photos import skipped_entries
from usvc.prepare.new_scene import NewSceneOptions, add_scene
from usvc.prepare.options import SceneOptions

register_configs()


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"  # a copy: the real checkout's conf/, params.yaml and data/ are never touched
    shutil.copytree(REPO / "conf", root / "conf")
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, root / name)
    return root


def make_photos(folder: Path, n: int = 9, **exif) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        photo(folder / f"IMG_{i:04d}.jpg", size=(80, 60), **(exif or {"a405": 26}))
    return folder


@pytest.fixture
def photos(tmp_path: Path) -> Path:
    return make_photos(tmp_path / "capture")


def snapshot(root: Path) -> tuple[list[str], str]:
    """Every path under the checkout (hidden temporaries and locks included) and params.yaml."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")), (root / "params.yaml").read_text()


def map_cli(checkout: Path, monkeypatch, *args: str | Path) -> int:
    monkeypatch.chdir(checkout)
    return cli.main(["map", *map(str, args), "--no-run"])


def scene_problems(**values) -> list[str]:
    """What the prepare stage's config check (SceneOptions.problems) says about these scene values."""
    return SceneOptions(**{"format": "images", "path": "x", "split": "every_nth", **values}).problems()


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def registered(checkout: Path, name: str) -> bool:
    parts = ((checkout / "conf/scene" / f"{name}.yaml").is_file(), (checkout / "data/raw" / name).is_dir(),
             name in yaml.safe_load((checkout / "params.yaml").read_text())["scenes"])
    assert len(set(parts)) == 1, f"half-registered: {parts}"
    return parts[0]


# ------------------------------------------------------------------ 1. names

@pytest.mark.parametrize("name, message", [
    ("base_scene", "reserved for usvc's config schemas"),
    ("base_kitchen", "reserved for usvc's config schemas"),
    ("config", r"taken by .*conf/config.yaml \(a config file of conf/\)"),
    ("sfm", r"taken by .*conf/sfm \(a config group of conf/\)"),
    ("mini", r"scene 'mini' already exists \(.*conf/scene/mini.yaml\)"),
    ("office", r"scene 'office' already exists"),
    ("class", r"reserved \(a Python keyword\)"),
    ("null", r"reserved \(a YAML/Hydra literal\)"),
    ("hydra", r"reserved \(a Hydra key\)"),
    ("raw", "data/raw/ holds"),
    ("Kitchen", "use lower-case letters"),
    ("kit-chen", "use lower-case letters"),
    ("_self_", "use lower-case letters"),
    ("k" * 65, "at most 64 characters"),
])
def test_names_that_collide_or_are_reserved_are_refused_before_anything_is_written(
        checkout: Path, photos: Path, monkeypatch, capsys, name: str, message: str) -> None:
    before = snapshot(checkout)
    with pytest.raises(UsvcError, match=message):
        add_scene(photos, checkout, NewSceneOptions(name))
    assert map_cli(checkout, monkeypatch, photos, "--name", name) == 1
    assert "usvc map: error: " in one_error_line(capsys)
    assert snapshot(checkout) == before


def test_the_scene_configs_still_compose_after_a_refused_base_scene(checkout: Path, photos: Path) -> None:
    with pytest.raises(UsvcError):
        add_scene(photos, checkout, NewSceneOptions("base_scene"))
    assert not (checkout / "conf/scene/base_scene.yaml").exists()
    with initialize_config_dir(config_dir=str(checkout / "conf"), version_base=None):
        validate(compose("config", overrides=["scene=mini"]))


# ------------------------------------------------------------------ 2, 3. working width, metric scale

@pytest.mark.parametrize("width, message", [
    (100000, "wider than any camera's photos: at most 16384 px"),
    (16385, "at most 16384 px"),
    (1, "width too small: at least 64 px"),
    (63, "width too small: at least 64 px"),
    (-5, "width too small: at least 64 px"),
])
def test_working_widths_no_camera_has_are_refused(checkout: Path, photos: Path, monkeypatch, capsys,
                                                  width: int, message: str) -> None:
    before = snapshot(checkout)
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen", "--working-width", width) == 1
    assert message in one_error_line(capsys)
    assert snapshot(checkout) == before
    assert [p.split("=")[0] for p in scene_problems(working_width=width)] == ["working_width"]  # the stage too


@pytest.mark.parametrize("width", [0, 64, 16384])
def test_working_widths_at_the_bounds_are_accepted(checkout: Path, photos: Path, width: int) -> None:
    add_scene(photos, checkout, NewSceneOptions("kitchen", working_width=width))
    assert yaml.safe_load((checkout / "conf/scene/kitchen.yaml").read_text())["working_width"] == width
    assert scene_problems(working_width=width) == []


@pytest.mark.parametrize("scale", ["inf", "-inf", "nan", "0", "-1"])
def test_non_finite_or_non_positive_metric_scales_are_refused(checkout: Path, photos: Path, monkeypatch, capsys,
                                                              scale: str) -> None:
    before = snapshot(checkout)
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen", f"--metric-scale={scale}") == 1
    assert "--metric-scale" in one_error_line(capsys)
    assert snapshot(checkout) == before
    assert [p.split("=")[0] for p in scene_problems(metric_scale=float(scale))] == ["metric_scale"]  # the stage too


def test_a_finite_metric_scale_is_written(checkout: Path, photos: Path) -> None:
    add_scene(photos, checkout, NewSceneOptions("kitchen", metric_scale=2.5))
    assert yaml.safe_load((checkout / "conf/scene/kitchen.yaml").read_text())["metric_scale"] == 2.5


# ------------------------------------------------------------------ 4. files that are not photos

def test_files_that_are_not_photos_are_listed_in_one_warning(checkout: Path, photos: Path, caplog) -> None:
    (photos / "IMG_0100.heic").write_bytes(b"\x00\x00\x00\x18ftypheic")
    (photos / "notes.txt").write_text("tripod at 1.2 m")
    (photos / "raw").mkdir()
    (photos / ".DS_Store").write_bytes(b"\x00")  # hidden: not listed
    with caplog.at_level(logging.WARNING):
        added = add_scene(photos, checkout, NewSceneOptions("kitchen"))
    assert added["photos"] == 9
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "skipped" in r.getMessage()]
    assert len(warnings) == 1, warnings
    assert "skipped 3 of the entries" in warnings[0]
    assert "IMG_0100.heic (unsupported type .heic)" in warnings[0]
    assert "notes.txt (unsupported type .txt)" in warnings[0]
    assert "raw/ (a folder" in warnings[0]
    assert skipped_entries(photos) == {"IMG_0100.heic": "unsupported type .heic", "notes.txt": "unsupported type .txt",
                                       "raw/": "a folder (subfolders are not read)"}


@pytest.mark.slow
def test_skipped_files_are_listed_in_prepared_json(tmp_path: Path) -> None:
    """The prepare stage reads the folder too: prepared.json lists what it skipped (SfM replaced by a stub
    here, the stage's own code runs unchanged)."""
    folder = make_photos(tmp_path / "capture", 4)
    (folder / "IMG_0100.heic").write_bytes(b"heic")
    argv = ["prepare", f"--config-path={REPO / 'conf'}", "scene=office", "scene.name=kit", "scene.format=images",
            f"scene.path={folder}", "scene.split=every_nth", f"data_dir={tmp_path / 'data'}",
            f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}"]
    code = ("import sys, stages.prepare as stage, usvc.prepare.run as step\n"
            "step.prepare_scene = lambda scene, out, *a, **k: (out.joinpath('ok').write_text('x'), "
            "{'frames': len(scene.frames)})[1]\n"
            f"sys.argv = {argv!r}\n"
            "stage.main()\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert "skipped 1 of the entries" in proc.stdout + proc.stderr
    prepared = json.loads((tmp_path / "results/kit/prepared.json").read_text())
    assert prepared["frames"] == 4
    assert prepared["skipped"] == {"IMG_0100.heic": "unsupported type .heic"}


# ------------------------------------------------------------------ 5. symbolic links

@pytest.mark.parametrize("links, bad", [
    ({"loop": "loop"}, "loop"),  # a link to itself
    ({"a": "b", "b": "a"}, "a"),  # two links to each other
    ({"up": ".."}, "up"),  # a folder link to a folder it is in: copytree would recurse forever
])
def test_a_symlink_loop_is_one_line_naming_the_link(checkout: Path, photos: Path, monkeypatch, capsys,
                                                     links: dict[str, str], bad: str) -> None:
    for link, target in links.items():
        (photos / link).symlink_to(target)
    before = snapshot(checkout)
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen") == 1
    err = one_error_line(capsys)
    assert "symbolic link loop" in err and str(photos / bad) in err and "[(" not in err
    assert snapshot(checkout) == before


def test_a_broken_link_is_one_line_and_good_links_are_followed(checkout: Path, photos: Path, tmp_path: Path) -> None:
    (photos / "gone.jpg").symlink_to(tmp_path / "nowhere.jpg")
    with pytest.raises(UsvcError, match=r"broken symbolic link in the photo folder: .*gone.jpg -> "):
        add_scene(photos, checkout, NewSceneOptions("kitchen"))
    (photos / "gone.jpg").unlink()
    extra = make_photos(tmp_path / "elsewhere", 1)
    (photos / "IMG_0050.jpg").symlink_to(extra / "IMG_0000.jpg")
    assert add_scene(photos, checkout, NewSceneOptions("kitchen"))["photos"] == 10
    assert (checkout / "data/raw/kitchen/IMG_0050.jpg").is_file()
    assert not (checkout / "data/raw/kitchen/IMG_0050.jpg").is_symlink()


# ------------------------------------------------------------------ 6. EXIF focal length

def test_an_absurd_exif_focal_is_named_and_no_exif_ignores_it(checkout: Path, tmp_path: Path, monkeypatch,
                                                               capsys) -> None:
    folder = make_photos(tmp_path / "capture", 9, a405=1)  # FocalLengthIn35mmFilm = 1 mm: a 174 deg view
    before = snapshot(checkout)
    assert map_cli(checkout, monkeypatch, folder, "--name", "kitchen") == 1
    err = one_error_line(capsys)
    assert "IMG_0000.jpg" in err and "EXIF focal length (1 mm" in err and "173.6 deg" in err and "--no-exif" in err
    assert snapshot(checkout) == before

    assert map_cli(checkout, monkeypatch, folder, "--name", "kitchen", "--no-exif") == 0
    scene_yaml = yaml.safe_load((checkout / "conf/scene/kitchen.yaml").read_text())
    assert scene_yaml["exif_focal"] is False
    with initialize_config_dir(config_dir=str(checkout / "conf"), version_base=None):
        cfg = compose("config", overrides=["scene=kitchen"])
        validate(cfg)
    assert cfg.scene.exif_focal is False
    scene = load_scene("images", checkout / "data/raw/kitchen", "kitchen", "every_nth", 8, None, exif_focal=False)
    assert all(not f.focal_known and f.camera.params[0] == pytest.approx(1.2 * 80) for f in scene.frames)


def test_plausible_exif_focals_are_kept(tmp_path: Path) -> None:
    for f35 in (5, 26, 200):  # 148 deg (ultra wide) to 10 deg (telephoto)
        folder = make_photos(tmp_path / f"f{f35}", 4, a405=f35)
        scene = load_scene("images", folder, "s", "every_nth", 8)
        assert all(f.focal_known and f.camera.params[0] == pytest.approx(f35 / 36 * 80) for f in scene.frames)


def test_no_exif_is_for_photos_only(checkout: Path, photos: Path) -> None:
    with pytest.raises(UsvcError, match="--no-exif applies to --format images only"):
        add_scene(photos, checkout, NewSceneOptions("kitchen", format="llff", exif_focal=False))


# ------------------------------------------------------------------ 7. too few photos

@pytest.mark.parametrize("n", [1, 2, 3])
def test_too_few_photos_are_refused_at_once(checkout: Path, tmp_path: Path, monkeypatch, capsys, n: int) -> None:
    folder = make_photos(tmp_path / "capture", n)
    before = snapshot(checkout)
    assert map_cli(checkout, monkeypatch, folder, "--name", "kitchen") == 1
    assert f"need at least 4 photos (got {n})" in one_error_line(capsys)
    assert snapshot(checkout) == before
    make_photos(folder, 4)  # a retry with enough photos is not "already exists"
    assert map_cli(checkout, monkeypatch, folder, "--name", "kitchen") == 0
    assert registered(checkout, "kitchen")


def test_a_split_that_leaves_too_few_to_map_is_refused(checkout: Path, tmp_path: Path) -> None:
    folder = make_photos(tmp_path / "capture", 5)  # --split-n 2: photos 0, 2, 4 are queries, 2 left to map
    with pytest.raises(UsvcError, match="5 photos with --split-n 2 leave 2 to map: need at least 3"):
        add_scene(folder, checkout, NewSceneOptions("kitchen", split_n=2))
    assert not registered(checkout, "kitchen")


# ------------------------------------------------------------------ 8. all or nothing

def test_a_truncated_photo_is_named_before_anything_is_written(checkout: Path, photos: Path) -> None:
    good = (photos / "IMG_0004.jpg").read_bytes()
    (photos / "IMG_0004.jpg").write_bytes(good[: len(good) // 2])
    before = snapshot(checkout)
    with pytest.raises(UsvcError, match=r"IMG_0004.jpg: truncated or corrupt JPEG"):
        add_scene(photos, checkout, NewSceneOptions("kitchen"))
    assert snapshot(checkout) == before
    (photos / "IMG_0004.jpg").write_bytes(good)
    add_scene(photos, checkout, NewSceneOptions("kitchen"))
    assert registered(checkout, "kitchen")


@pytest.mark.parametrize("where", ["_copy_tree", "_scene_yaml", "_add_to_params"])
@pytest.mark.parametrize("error", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()])
def test_a_failure_midway_leaves_nothing_and_a_retry_succeeds(checkout: Path, photos: Path, monkeypatch, capsys,
                                                              where: str, error: BaseException) -> None:
    before = snapshot(checkout)
    real = getattr(new_scene, where)

    def fail(*args, **kwargs):
        real(*args, **kwargs)  # did its part (photos copied, yaml made, params.yaml replaced), then fails
        raise error

    monkeypatch.setattr(new_scene, where, fail)
    code = map_cli(checkout, monkeypatch, photos, "--name", "kitchen")
    err = one_error_line(capsys)
    if isinstance(error, KeyboardInterrupt):
        assert code == 130 and "interrupted, nothing written" in err
    else:
        assert code == 1 and "No space left on device" in err and "nothing was written" in err
    assert snapshot(checkout) == before
    monkeypatch.setattr(new_scene, where, real)
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen") == 0
    assert registered(checkout, "kitchen")
    assert not (checkout / new_scene.LOCK_FILE).exists()


def test_sigterm_while_registering_is_undone(checkout: Path, photos: Path, monkeypatch) -> None:
    before = snapshot(checkout)
    real = new_scene._add_to_params

    def killed(params: Path, name: str) -> None:
        real(params, name)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises here
        raise AssertionError("SIGTERM was not turned into an undo")

    monkeypatch.setattr(new_scene, "_add_to_params", killed)
    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        add_scene(photos, checkout, NewSceneOptions("kitchen"))
    assert signal.getsignal(signal.SIGTERM) == handler  # restored
    assert snapshot(checkout) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_scene_folder_leaves_nothing(checkout: Path, photos: Path, monkeypatch, capsys) -> None:
    before = snapshot(checkout)
    (checkout / "conf/scene").chmod(0o555)
    try:
        assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen") == 1
        assert "conf/scene is not writable" in one_error_line(capsys)
        assert snapshot(checkout) == before
    finally:
        (checkout / "conf/scene").chmod(0o755)
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen") == 0
    assert registered(checkout, "kitchen")


def test_two_maps_of_one_name_at_once_one_wins(checkout: Path, photos: Path, monkeypatch) -> None:
    real = new_scene._copy_tree

    def slow(*args, **kwargs):
        time.sleep(0.3)  # both have passed their checks; the lock decides
        real(*args, **kwargs)

    monkeypatch.setattr(new_scene, "_copy_tree", slow)
    start = threading.Barrier(2)
    results: list[object] = []

    def run() -> None:
        start.wait()
        try:
            results.append(add_scene(photos, checkout, NewSceneOptions("kitchen"))["name"])
        except UsvcError as err:
            results.append(str(err))

    threads = [threading.Thread(target=run) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert sorted(map(str, results))[0].startswith("kitchen"), results
    assert "scene 'kitchen' already exists" in sorted(map(str, results))[1], results
    assert registered(checkout, "kitchen")
    assert yaml.safe_load((checkout / "params.yaml").read_text())["scenes"] == ["mini", "kitchen"]
    assert sorted(p.name for p in (checkout / "data/raw").iterdir()) == ["kitchen"]  # no .partial left
    assert not (checkout / new_scene.LOCK_FILE).exists()


def test_two_maps_of_different_names_at_once_both_land_in_params(checkout: Path, photos: Path, monkeypatch) -> None:
    real = new_scene._params_with

    def slow(*args, **kwargs):
        time.sleep(0.3)  # params.yaml read, not yet written: without the lock the other's entry would be lost
        return real(*args, **kwargs)

    monkeypatch.setattr(new_scene, "_params_with", slow)
    start = threading.Barrier(2)
    errors: list[BaseException] = []

    def run(name: str) -> None:
        start.wait()
        try:
            add_scene(photos, checkout, NewSceneOptions(name))
        except BaseException as err:  # noqa: BLE001 - reported below
            errors.append(err)

    threads = [threading.Thread(target=run, args=(n,)) for n in ("kitchen", "hall")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    assert sorted(yaml.safe_load((checkout / "params.yaml").read_text())["scenes"]) == ["hall", "kitchen", "mini"]
    assert registered(checkout, "kitchen") and registered(checkout, "hall")


@pytest.mark.slow
def test_two_processes_of_one_name_at_once(checkout: Path, photos: Path) -> None:
    """The same race as the real CLI runs it: two processes, one winner, one 'already exists'."""
    cmd = [sys.executable, "-m", "usvc.cli", "--threads", "1", "map", str(photos), "--name", "kitchen", "--no-run"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen(cmd, cwd=checkout, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 1], outs
    loser = next(err for p, (_, err) in zip(procs, outs) if p.returncode == 1)
    assert "Traceback" not in loser, loser
    assert [line for line in loser.splitlines() if "error" in line.lower()] == [loser.splitlines()[-1]], loser
    assert loser.splitlines()[-1].startswith("usvc map: error: scene 'kitchen' already exists"), loser
    assert registered(checkout, "kitchen")
    assert sorted(p.name for p in (checkout / "data/raw").iterdir()) == ["kitchen"]



def test_a_failed_pipeline_says_the_scene_stays_and_how_to_go_on(checkout: Path, photos: Path, monkeypatch,
                                                                   capsys) -> None:
    """The scene is added before its pipeline runs: when a stage fails, `usvc map` says so and names
    the command that goes on (a second `usvc map --name` would find the name taken)."""
    monkeypatch.setattr(new_scene, "repro", lambda checkout, name: 1)
    monkeypatch.chdir(checkout)
    assert cli.main(["map", str(photos), "--name", "kitchen"]) == 1
    err = capsys.readouterr().err
    assert "the scene stays added" in err and "`dvc repro metrics@kitchen`" in err
    assert (checkout / "conf" / "scene" / "kitchen.yaml").is_file()
    assert map_cli(checkout, monkeypatch, photos, "--name", "kitchen") == 1
    assert "already exists" in capsys.readouterr().err
