"""Each bad input stops its stage with one line naming what is wrong, and leaves no artifact."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import REPO, shared_scene


@pytest.fixture
def llff(tmp_path) -> Path:
    """A tiny LLFF scene: office's first 9 poses with small textured images."""
    src = np.load(shared_scene("office") / "poses_bounds.npy")[:9].copy()
    root = tmp_path / "raw"
    (root / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(9):
        cv2.imwrite(str(root / "images" / f"img_{i}.png"), rng.integers(0, 255, (54, 96, 3), dtype=np.uint8))
    np.save(root / "poses_bounds.npy", src)
    return root


def _prepare(tmp_path: Path, root: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "stages.prepare", "scene=office", f"scene.path={root}", "scene.working_width=0",
         f"data_dir={tmp_path / 'data'}", f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}"],
        cwd=REPO, capture_output=True, text=True,
    )


def _assert_clean_failure(proc, tmp_path, *needles):
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1, out
    assert "Traceback" not in out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1, out
    for needle in needles:
        assert needle in errors[0], errors[0]
    assert not (tmp_path / "data" / "office").exists(), "not even an empty scene folder is left"
    assert not (tmp_path / "results" / "office" / "prepared.json").exists()


@pytest.mark.slow
def test_good_scene_prepares(tmp_path, llff):
    proc = _prepare(tmp_path, llff)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "data/office/prepared/scene.h5").is_file()


@pytest.mark.slow
def test_missing_image(tmp_path, llff):
    (llff / "images" / "img_3.png").unlink()
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "poses_bounds.npy", "8", "9")


@pytest.mark.slow
def test_unreadable_image(tmp_path, llff):
    (llff / "images" / "img_3.png").write_bytes(b"not a png")
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "img_3.png")


@pytest.mark.slow
def test_pose_count_mismatch(tmp_path, llff):
    np.save(llff / "poses_bounds.npy", np.load(llff / "poses_bounds.npy")[:8])
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "poses_bounds.npy")


@pytest.mark.slow
def test_non_rotation_pose(tmp_path, llff):
    pb = np.load(llff / "poses_bounds.npy")
    pb[2, 0] *= 3.0
    np.save(llff / "poses_bounds.npy", pb)
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "row 2", "not a rotation")


@pytest.mark.slow
def test_non_finite_pose(tmp_path, llff):
    pb = np.load(llff / "poses_bounds.npy")
    pb[4, 3] = np.nan
    np.save(llff / "poses_bounds.npy", pb)
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "row 4", "not finite")


@pytest.mark.slow
def test_cropped_images_are_refused(tmp_path, llff):
    """Images cropped to another aspect than the poses' (h, w): an anisotropic focal, refused."""
    rng = np.random.default_rng(1)
    for i in range(9):
        cv2.imwrite(str(llff / "images" / f"img_{i}.png"), rng.integers(0, 255, (54, 80, 3), dtype=np.uint8))
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "row 0", "80x54", "1920x1080", "cropped images?")


@pytest.mark.slow
def test_every_mapping_image_the_same_photo_is_refused(tmp_path, llff):
    same = (llff / "images" / "img_0.png").read_bytes()
    for i in range(1, 9):
        (llff / "images" / f"img_{i}.png").write_bytes(same)
    _assert_clean_failure(_prepare(tmp_path, llff), tmp_path, "mapping images differ", "pixel-identical copies")


@pytest.mark.slow
def test_unknown_format(tmp_path, llff):
    proc = subprocess.run(
        [sys.executable, "-m", "stages.prepare", "scene=office", f"scene.path={llff}", "scene.format=nerf",
         f"data_dir={tmp_path / 'data'}", f"hydra.run.dir={tmp_path / 'log'}"],
        cwd=REPO, capture_output=True, text=True,
    )
    _assert_clean_failure(proc, tmp_path, "scene.format='nerf'")


@pytest.mark.slow
def test_ctrl_c_prints_one_line_and_leaves_nothing(tmp_path):
    """SIGINT while the generate stage renders: one line, exit 130, no artifact, no temporary dir."""
    import signal
    import time

    raw = tmp_path / "raw" / "mini"
    proc = subprocess.Popen(
        [sys.executable, "-m", "stages.generate", "scene=mini", f"scene.path={raw}",
         f"results_dir={tmp_path / 'results'}", f"hydra.run.dir={tmp_path / 'log'}"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        # a runner started in the background (nohup, `&`) ignores SIGINT and its children inherit
        # that: give the stage the default disposition, so this tests the stage, not the runner
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 120
    while not list(raw.parent.glob(".mini.tmp-*")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)  # wait until it is writing frames
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, out
    assert "Traceback" not in out
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "generate interrupted, nothing written" in errors[0], out
    assert not raw.exists() and not list(raw.parent.glob(".mini.tmp-*"))
    assert not (tmp_path / "results" / "mini" / "generate.json").exists()
