"""The stages are as strict as `usvc map`: a scene name that would leave data/, a read-only or full
disk, an artifact whose header declares more than its file holds: each is one line, and nothing
half-written is left. (A learned pose never computed: tests/test_metrics_stage.py.)"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import REPO

from usvc.core.atomic import WriteError
from usvc.core.errors import UsvcError
from usvc.pipeline.config import ConfigError, compose_for_script
from usvc.pipeline.paths import RESERVED_SCENE_NAMES, SCENE_NAME_RULE, scene_name_problem


def _errors(proc: subprocess.CompletedProcess) -> list[str]:
    out = proc.stdout + proc.stderr
    assert "Traceback" not in out, out
    return [line for line in out.splitlines() if "ERROR" in line]


# ------------------------------------------------------------------ 1. scene names

@pytest.mark.parametrize("name", ["../../evil", "", "a/b", "a\\b", "..", "Mini", "raw", "base_scene", "class"])
def test_scene_names_usvc_map_refuses_are_refused_by_the_stages(name):
    with pytest.raises(ConfigError, match=r"config key scene.name="):
        compose_for_script("mini", [f"scene.name={name}"] if name else ["scene.name=''"])


def test_the_stages_and_usvc_map_share_the_name_rule(tmp_path):
    """One rule: usvc map's check (for names that are free) refuses exactly what the stages refuse."""
    from usvc.prepare import new_scene

    assert scene_name_problem("mini\n")  # fullmatch: not even a trailing newline
    assert SCENE_NAME_RULE.fullmatch("kitchen") and "raw" in RESERVED_SCENE_NAMES
    (tmp_path / "conf" / "scene").mkdir(parents=True)
    (tmp_path / "params.yaml").write_text("scenes:\n  - mini\n")
    for name in ("kitchen", "a1", "../../evil", "a/b", "", "raw", "null", "base_x", "class", "x" * 65, "Kit", "mini\n"):
        try:
            new_scene.check_name(name, tmp_path)
            refused = False
        except UsvcError:
            refused = True
        assert refused == bool(scene_name_problem(name)), name


@pytest.mark.slow
def test_a_scene_name_that_leaves_the_data_folder_writes_nothing(tmp_path):
    data = tmp_path / "a" / "b" / "data"
    proc = subprocess.run([sys.executable, "-m", "stages.prepare", "scene=mini", "scene.name=../../evil", "threads=1",
                           f"data_dir={data}", f"results_dir={tmp_path / 'results'}",
                           f"hydra.run.dir={tmp_path / 'log'}"], cwd=REPO, capture_output=True, text=True)
    errors = _errors(proc)
    assert proc.returncode == 1 and len(errors) == 1, proc.stdout + proc.stderr
    assert "scene.name='../../evil'" in errors[0], errors[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log"], list(tmp_path.rglob("*"))


# ------------------------------------------------------------------ 2. read-only or full disk

# Root ignores file permissions (chmod a-w is no test), so the disk's answer is simulated: every
# write (open for writing, mkdir) under `root` fails with `err`, as a read-only mount or a full disk does.
_FAILING_DISK = """
import builtins, errno, io, os, runpy, sys
root, err, what = sys.argv[1], getattr(errno, sys.argv[2]), sys.argv[3]
real_open, real_mkdir = builtins.open, os.mkdir
def under(p):
    return isinstance(p, (str, bytes, os.PathLike)) and os.path.abspath(os.fsdecode(p)).startswith(root)
def fail(p):
    raise OSError(err, os.strerror(err), os.fsdecode(p))
def guarded_open(file, mode="r", *a, **k):
    if under(file) and any(c in mode for c in "wax+"):
        fail(file)
    return real_open(file, mode, *a, **k)
def guarded_mkdir(path, *a, **k):
    if under(path) and what == "mkdir":
        fail(path)
    return real_mkdir(path, *a, **k)
builtins.open = io.open = guarded_open
os.mkdir = guarded_mkdir
sys.argv = ["gaussians", *sys.argv[4:]]
runpy.run_module("stages.gaussians", run_name="__main__")
"""


def _stage_on_failing_disk(tmp_path: Path, root: Path, err: str, what: str) -> subprocess.CompletedProcess:
    """The gaussians stage (with rendered views off it writes one small file: no inputs needed)."""
    return subprocess.run([sys.executable, "-c", _FAILING_DISK, str(root), err, what, "scene=mini", "threads=1",
                           "buffer.rendered_views=false", f"data_dir={tmp_path / 'data'}",
                           f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}"],
                          cwd=REPO, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})


@pytest.mark.parametrize("err, reason", [("EROFS", "Read-only file system"), ("EACCES", "Permission denied")])
def test_a_read_only_data_folder_is_one_line_naming_the_artifact(tmp_path, err, reason):
    proc = _stage_on_failing_disk(tmp_path, tmp_path / "data", err, "mkdir")
    errors = _errors(proc)
    assert proc.returncode == 1 and len(errors) == 1, proc.stdout + proc.stderr
    assert f"cannot write {tmp_path / 'data' / 'mini' / 'gaussians'}: {reason}, nothing written" in errors[0], errors[0]
    assert not (tmp_path / "data").exists() and not (tmp_path / "results" / "mini" / "gaussians.json").exists()


def test_a_full_disk_names_the_artifact_not_its_temporary_folder(tmp_path):
    proc = _stage_on_failing_disk(tmp_path, tmp_path / "data", "ENOSPC", "open")
    errors = _errors(proc)
    assert proc.returncode == 1 and len(errors) == 1, proc.stdout + proc.stderr
    assert "No space left on device" in errors[0] and ".tmp-" not in errors[0], errors[0]
    assert f"in {tmp_path / 'data' / 'mini' / 'gaussians'}" in errors[0], errors[0]
    assert [p for p in (tmp_path / "data").rglob("*") if not p.is_dir()] == []


def test_a_read_only_results_folder_leaves_no_artifact(tmp_path):
    proc = _stage_on_failing_disk(tmp_path, tmp_path / "results", "EROFS", "open")
    errors = _errors(proc)
    assert proc.returncode == 1 and len(errors) == 1, proc.stdout + proc.stderr
    record = tmp_path / "results" / "mini" / "gaussians.json"
    assert f"cannot write {record}: Read-only file system" in errors[0], errors[0]
    assert not (tmp_path / "data" / "mini" / "gaussians").exists()


# ------------------------------------------------------------------ 3. a full disk while prepare writes images

def test_a_full_disk_while_writing_an_image_names_the_folder_and_the_reason(tmp_path, monkeypatch):
    from usvc.prepare import working_images

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    tmp = tmp_path / "data" / "mini" / f".prepared.tmp-{os.getpid()}"
    monkeypatch.setattr(working_images, "open", full, raising=False)
    with pytest.raises(WriteError) as caught:
        working_images.write_image(tmp / "images" / "0001.png", np.zeros((8, 8, 3), np.uint8))
    assert str(caught.value) == (f"cannot write image images/0001.png in {tmp_path / 'data' / 'mini' / 'prepared'}: "
                                 "No space left on device")
    with pytest.raises(WriteError, match=r"cannot write image 0001.png in /tmp \(the temporary folder"):
        working_images.write_image(tmp_path / "0001.png", np.zeros((8, 8, 3), np.uint8),
                                   "/tmp (the temporary folder SfM poses the photos in)")


def test_an_image_written_in_memory_has_the_bytes_imwrite_writes(tmp_path):
    import cv2

    from usvc.prepare.working_images import write_image

    image = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    for name, params in (("a.png", []), ("a.JPG", [cv2.IMWRITE_JPEG_QUALITY, 95])):
        write_image(tmp_path / "mine" / name, image)
        cv2.imwrite(str(tmp_path / name), image, params)
        assert (tmp_path / "mine" / name).read_bytes() == (tmp_path / name).read_bytes(), name


# ------------------------------------------------------------------ 4. declared shapes against the file's size

def _landmarks_file(path: Path) -> Path:
    from usvc.landmarks.landmark_table import Landmarks
    from usvc.landmarks.landmarks_file import write_landmarks

    lm = Landmarks("scene", np.zeros((4, 3)), np.zeros((4, 128), np.uint8),
                   np.tile([0, 0, 1.0], (4, 1)).astype(np.float32), np.full(4, 5.0, np.float32),
                   np.full(4, 2, np.int32), 6)
    write_landmarks(path, lm)
    return path


def _redeclare(path: Path, name: str, shape: tuple[int, ...], dtype: str, **kwargs) -> None:
    """Replace dataset `name` by one that only declares `shape` (no data written: the file stays small)."""
    with h5py.File(path, "r+") as h5:
        del h5[name]
        h5.create_dataset(name, shape=shape, dtype=dtype, **kwargs)


def test_a_billion_declared_rows_are_refused_from_the_header(tmp_path):
    """The 22.4 GiB xyz of a 10 MB file: refused by reading the header alone (nothing allocated)."""
    from usvc.core.h5_file import declared_size_problem, read_h5

    path = _landmarks_file(tmp_path / "landmarks.h5")
    _redeclare(path, "xyz", (10**9, 3), "f8")
    with h5py.File(path, "r") as h5:
        why = declared_size_problem(h5["xyz"], path.stat().st_size)
    assert why.startswith("declares 1000000000x3 float64 (22.4 GiB), but the file is "), why
    with pytest.raises(UsvcError, match=r"landmarks.h5: landmarks dataset xyz declares 1000000000x3 float64 "
                                        r"\(22.4 GiB\), but the file is .* with 0 bytes stored: "
                                        r"corrupt or crafted file"):
        with read_h5(path, "landmarks"):
            pass


# Declared sizes a build without the check would still survive reading (a few hundred MB of fill values).
@pytest.mark.parametrize("name, shape, dtype, kwargs", [
    ("xyz", (10**7, 3), "f8", {}),  # contiguous: 229 MiB declared, nothing stored
    ("descriptor", (10**6, 128), "u1", {"chunks": (1024, 128), "compression": "gzip"}),  # compressed
])
def test_a_dataset_declaring_more_than_the_file_holds_is_refused_before_reading(tmp_path, name, shape, dtype, kwargs):
    from usvc.landmarks.landmarks_file import read_landmarks

    path = _landmarks_file(tmp_path / "landmarks.h5")
    _redeclare(path, name, shape, dtype, **kwargs)
    assert path.stat().st_size < 1_000_000
    with pytest.raises(UsvcError) as caught:
        read_landmarks(path)
    line = str(caught.value)
    assert "\n" not in line and str(path) in line and f"dataset {name} declares" in line, line


def test_landmark_tables_of_different_row_counts_are_refused_before_reading(tmp_path):
    from usvc.landmarks.landmarks_file import read_landmarks

    path = _landmarks_file(tmp_path / "landmarks.h5")
    with h5py.File(path, "r+") as h5:
        del h5["track_length"]
        h5["track_length"] = np.full(5, 2, np.int32)
    with pytest.raises(UsvcError, match=r"landmarks dataset track_length declares 5 rows, xyz 4"):
        read_landmarks(path)


def test_intact_artifacts_pass_the_size_check(tmp_path):
    from usvc.landmarks.landmarks_file import read_landmarks

    assert len(read_landmarks(_landmarks_file(tmp_path / "landmarks.h5")).xyz) == 4
