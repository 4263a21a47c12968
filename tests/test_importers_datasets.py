"""ACE layout, 7-Scenes and Cambridge importers, and format dispatch. Importers: each fixture is written in the format's exact published layout from known
ground-truth cameras, and the imported scene must reproject a known world point to the same
pixel (1e-6 px). That checks axes, pose direction, focal scaling, principal point and frame
order together, rather than comparing matrices by eye.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from importer_fixtures import (  # noqa: F401
    GL_FROM_CV,
    SHARED,
    X_WORLD,
    GtCam,
    assert_reprojects,
    cam_to_world_matrix,
    make_gt,
    project,
    write_image,
    write_pose_txt,
)
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.core.errors import SceneError, UsvcError
from usvc.core.scene import Camera, Frame, check_rotation
from usvc.prepare.importers import FORMATS, load_scene

# ---------------------------------------------------------------- ACE layout

def ace_scene(root: Path) -> dict[str, GtCam]:
    """ACE layout with one-number calibration in train and a 3x3 K in test."""
    W, H = 32, 24
    gts = {}
    for split, n in (("train", 3), ("test", 2)):
        for i in range(n):
            stem = f"seq-01-frame-{i:06d}"
            if split == "train":
                cam = Camera("PINHOLE", W, H, (30.0, 30.0, W / 2, H / 2))
                calib = "30.0\n"
            else:
                cam = Camera("PINHOLE", W, H, (31.0, 32.0, 15.0, 13.0))
                calib = "31 0 15\n0 32 13\n0 0 1\n"
            gt = make_gt(100 + len(gts), cam)
            gts[f"{split}/rgb/{stem}.color.png"] = gt
            write_image(root / split / "rgb" / f"{stem}.color.png", W, H)
            write_pose_txt(root / split / "poses" / f"{stem}.pose.txt", cam_to_world_matrix(gt))
            (root / split / "calibration").mkdir(parents=True, exist_ok=True)
            (root / split / "calibration" / f"{stem}.calibration.txt").write_text(calib)
            (root / split / "depth").mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.full((H, W), 1500, dtype=np.uint16)).save(root / split / "depth" / f"{stem}.depth.png")
    return gts


def test_ace_reprojects_given_split_and_depth(tmp_path: Path) -> None:
    gts = ace_scene(tmp_path)
    scene = load_scene("ace", tmp_path, "toy")
    assert scene.metric_scale == 1.0
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"] * 2
    for frame in scene.frames:
        assert frame.depth_path is not None and frame.depth_path.is_file()
        assert frame.depth_scale == 0.001
        assert_reprojects(frame, gts[frame.name])
    nth = load_scene("ace", tmp_path, "toy", "every_nth", 2)
    assert [f.split for f in nth.frames] == ["test", "train", "test", "train", "test"]


def test_ace_count_mismatch(tmp_path: Path) -> None:
    ace_scene(tmp_path)
    write_pose_txt(tmp_path / "train/poses/seq-01-frame-000009.pose.txt", np.eye(4))
    with pytest.raises(SceneError, match=r"train/poses: 4 files but .*train/rgb has 3 images"):
        load_scene("ace", tmp_path, "toy")


def test_ace_unparseable_pose(tmp_path: Path) -> None:
    ace_scene(tmp_path)
    (tmp_path / "test/poses/seq-01-frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 x\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(SceneError, match=r"seq-01-frame-000001\.pose\.txt: not a numeric matrix"):
        load_scene("ace", tmp_path, "toy")


def test_ace_empty_split(tmp_path: Path) -> None:
    ace_scene(tmp_path)
    for sub in ("rgb", "poses", "calibration", "depth"):
        for p in (tmp_path / "test" / sub).iterdir():
            p.unlink()
    with pytest.raises(SceneError, match="'toy': the 'test' split is empty"):
        load_scene("ace", tmp_path, "toy")


# ---------------------------------------------------------------- 7-Scenes

SEVEN_CAM = Camera("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))


def seven_scenes(root: Path) -> dict[str, GtCam]:
    gts = {}
    for seq in (1, 2):
        for idx in (0, 10, 2):
            name = f"seq-{seq:02d}/frame-{idx:06d}"
            gt = make_gt(200 + len(gts), SEVEN_CAM)
            gts[f"{name}.color.png"] = gt
            write_image(root / f"{name}.color.png", 8, 6)
            write_pose_txt(root / f"{name}.pose.txt", cam_to_world_matrix(gt))
            Image.fromarray(np.zeros((6, 8), dtype=np.uint16)).save(root / f"{name}.depth.png")
    (root / "TrainSplit.txt").write_text("sequence1\n")
    (root / "TestSplit.txt").write_text("sequence2\n")
    return gts


def test_seven_scenes_reprojects_with_given_split(tmp_path: Path) -> None:
    gts = seven_scenes(tmp_path)
    scene = load_scene("7scenes", tmp_path, "chess")
    assert scene.metric_scale == 1.0
    assert [f.name for f in scene.frames][:3] == [
        "seq-01/frame-000000.color.png", "seq-01/frame-000002.color.png", "seq-01/frame-000010.color.png"]
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"] * 3
    for frame in scene.frames:
        assert frame.depth_scale == 0.001 and frame.depth_path is not None
        assert_reprojects(frame, gts[frame.name])
    nth = load_scene("7scenes", tmp_path, "chess", "every_nth", 4, metric_scale=2.0)
    assert nth.metric_scale == 2.0
    assert [f.split for f in nth.frames] == ["test", "train", "train", "train", "test", "train"]


def test_seven_scenes_missing_pose_file(tmp_path: Path) -> None:
    seven_scenes(tmp_path)
    (tmp_path / "seq-02/frame-000010.pose.txt").unlink()
    with pytest.raises(SceneError, match=r"missing file .*seq-02/frame-000010\.pose\.txt"):
        load_scene("7scenes", tmp_path, "chess")


def test_seven_scenes_missing_sequence(tmp_path: Path) -> None:
    seven_scenes(tmp_path)
    (tmp_path / "TestSplit.txt").write_text("sequence2\nsequence3\n")
    with pytest.raises(SceneError, match=r"TestSplit\.txt: sequence folder .*seq-03 does not exist"):
        load_scene("7scenes", tmp_path, "chess")


def test_seven_scenes_non_rotation_pose(tmp_path: Path) -> None:
    seven_scenes(tmp_path)
    write_pose_txt(tmp_path / "seq-01/frame-000002.pose.txt", np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(SceneError, match=r"frame-000002\.pose\.txt: .*not a rotation"):
        load_scene("7scenes", tmp_path, "chess")


# ---------------------------------------------------------------- Cambridge Landmarks

def cambridge_scene(root: Path, nvm: bool = True) -> dict[str, GtCam]:
    """Images on disk at 1/10 of the 1920x1080 originals that the NVM focal refers to."""
    W, H = 192, 108
    header = "Visual Landmark Dataset V1\nImageFile, Camera Position [X Y Z W P Q R]\n\n"
    gts: dict[str, GtCam] = {}
    nvm_lines = []
    for split, names in (("train", ["seq1/frame00002.png", "seq1/frame00010.png"]), ("test", ["seq2/frame00001.png"])):
        lines = []
        for name in names:
            focal = 1650.0 + 10 * len(gts)
            gt = make_gt(300 + len(gts), Camera("SIMPLE_PINHOLE", W, H, (focal / 10, W / 2, H / 2)))
            gts[name] = gt
            write_image(root / name, W, H)
            qx, qy, qz, qw = Rotation.from_matrix(gt.R).as_quat()
            c = gt.center
            lines.append(f"{name} {c[0]:.17g} {c[1]:.17g} {c[2]:.17g} {qw:.17g} {qx:.17g} {qy:.17g} {qz:.17g}")
            nvm_lines.append(f"{name[:-4]}.jpg {focal} {qw} {qx} {qy} {qz} {c[0]} {c[1]} {c[2]} -0.05 0")
        (root / f"dataset_{split}.txt").write_text(header + "\n".join(lines) + "\n")
    if nvm:
        body = "\n".join(nvm_lines)
        (root / "reconstruction.nvm").write_text(f"NVM_V3\n\n{len(nvm_lines)}\n{body}\n\n0\n")
    return gts


def test_cambridge_reprojects_with_scaled_nvm_focal(tmp_path: Path) -> None:
    gts = cambridge_scene(tmp_path)
    scene = load_scene("cambridge", tmp_path, "kings")
    assert scene.metric_scale == 1.0
    assert [f.split for f in scene.frames] == ["train", "train", "test"]
    for frame in scene.frames:
        assert frame.camera.model == "SIMPLE_PINHOLE"
        assert frame.camera.principal_point == (96.0, 54.0)
        assert_reprojects(frame, gts[frame.name])
    nth = load_scene("cambridge", tmp_path, "kings", "every_nth", 2)
    assert [f.name for f in nth.frames] == ["seq1/frame00002.png", "seq1/frame00010.png", "seq2/frame00001.png"]


def test_cambridge_needs_nvm(tmp_path: Path) -> None:
    cambridge_scene(tmp_path, nvm=False)
    with pytest.raises(SceneError, match=r"reconstruction\.nvm is missing.*NVM model is needed"):
        load_scene("cambridge", tmp_path, "kings")


def test_cambridge_missing_image(tmp_path: Path) -> None:
    cambridge_scene(tmp_path)
    (tmp_path / "seq2/frame00001.png").unlink()
    with pytest.raises(SceneError, match=r"missing image .*seq2/frame00001\.png"):
        load_scene("cambridge", tmp_path, "kings")


def test_cambridge_unparseable_line(tmp_path: Path) -> None:
    cambridge_scene(tmp_path)
    with (tmp_path / "dataset_test.txt").open("a") as fh:
        fh.write("seq2/frame00002.png 1 2 3 nope 0 0 0\n")
    with pytest.raises(SceneError, match=r"dataset_test\.txt:5: pose values are not numbers"):
        load_scene("cambridge", tmp_path, "kings")


def test_cambridge_zero_quaternion(tmp_path: Path) -> None:
    cambridge_scene(tmp_path)
    with (tmp_path / "dataset_test.txt").open("a") as fh:
        fh.write("seq2/frame00001.png 1 2 3 0 0 0 0\n")
    with pytest.raises(SceneError, match=r"dataset_test\.txt \(seq2/frame00001\.png\): quaternion"):
        load_scene("cambridge", tmp_path, "kings")


# ---------------------------------------------------------------- dispatch

def test_unknown_format_lists_known_ones(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="'nerf'.*" + ".*".join(FORMATS)):
        load_scene("nerf", tmp_path, "toy")


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="nowhere"):
        load_scene("llff", tmp_path / "nowhere", "toy", "every_nth")


def test_bad_split_rule_and_n(tmp_path: Path) -> None:
    ace_scene(tmp_path)
    with pytest.raises(SceneError, match="split rule 'random'"):
        load_scene("ace", tmp_path, "toy", "random")
    with pytest.raises(SceneError, match="n >= 2"):
        load_scene("ace", tmp_path, "toy", "every_nth", 1)


def test_errors_are_usvc_errors() -> None:
    assert issubclass(SceneError, UsvcError)
