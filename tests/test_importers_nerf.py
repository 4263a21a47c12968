"""LLFF, transforms.json and COLMAP importers, and the real office scene. Importers: each fixture is written in the format's exact published layout from known
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

# ---------------------------------------------------------------- LLFF

LLFF_NAMES = ["IMG_2.jpg", "IMG_10.jpg", "IMG_1.jpg", "IMG_3.jpg"]  # lexicographic: 1, 10, 2, 3


def llff_scene(root: Path, stored_hw: tuple[int, int] = (60, 80), disk_wh: tuple[int, int] = (40, 30)) -> dict[str, GtCam]:
    """LLFF scene whose poses were 'estimated' at stored_hw while images on disk are disk_wh."""
    h, w = stored_hw
    W, H = disk_wh
    f_stored = 70.0
    gts = {}
    rows = []
    for i, name in enumerate(sorted(LLFF_NAMES)):
        cam = Camera("PINHOLE", W, H, (f_stored * W / w, f_stored * H / h, W / 2, H / 2))
        gt = make_gt(10 + i, cam)
        gts[f"images/{name}"] = gt
        Rc = gt.R_cam_to_world  # columns right, down, forward
        R_llff = np.stack([Rc[:, 1], Rc[:, 0], -Rc[:, 2]], axis=1)  # down, right, backwards
        m = np.concatenate([R_llff, gt.center[:, None], np.array([[h], [w], [f_stored]])], axis=1)
        rows.append(np.concatenate([m.reshape(-1), [0.5, 20.0]]))
        write_image(root / "images" / name, W, H)
    np.save(root / "poses_bounds.npy", np.array(rows, dtype=np.float64))
    return gts


def test_llff_reprojects_with_lexicographic_rows_and_scaled_focal(tmp_path: Path) -> None:
    gts = llff_scene(tmp_path)
    scene = load_scene("llff", tmp_path, "toy", "every_nth", 2)
    assert [f.name for f in scene.frames] == ["images/IMG_1.jpg", "images/IMG_10.jpg", "images/IMG_2.jpg", "images/IMG_3.jpg"]
    assert [f.split for f in scene.frames] == ["test", "train", "test", "train"]
    for frame in scene.frames:
        assert frame.image_path.is_absolute() and frame.image_path.is_file()
        assert frame.camera.model == "PINHOLE"
        assert frame.camera.principal_point == (20.0, 15.0)
        assert frame.camera.focal == pytest.approx((35.0, 35.0))
        assert_reprojects(frame, gts[frame.name])


def test_llff_given_split_is_an_error(tmp_path: Path) -> None:
    llff_scene(tmp_path)
    with pytest.raises(SceneError, match="toy.*every_nth"):
        load_scene("llff", tmp_path, "toy")


def test_llff_row_count_mismatch(tmp_path: Path) -> None:
    llff_scene(tmp_path)
    write_image(tmp_path / "images" / "IMG_9.jpg", 40, 30)
    with pytest.raises(SceneError, match=r"poses_bounds\.npy: 4 pose rows but 5 images"):
        load_scene("llff", tmp_path, "toy", "every_nth")


def test_llff_unreadable_pose_file(tmp_path: Path) -> None:
    llff_scene(tmp_path)
    (tmp_path / "poses_bounds.npy").write_bytes(b"not a numpy file")
    with pytest.raises(SceneError, match=r"poses_bounds\.npy: unreadable"):
        load_scene("llff", tmp_path, "toy", "every_nth")


def test_llff_wrong_shape(tmp_path: Path) -> None:
    llff_scene(tmp_path)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((4, 15)))
    with pytest.raises(SceneError, match=r"poses_bounds\.npy: expected a numeric \(N, 17\)"):
        load_scene("llff", tmp_path, "toy", "every_nth")


@pytest.mark.parametrize("bad", ["nan_pose", "scaled_rotation", "zero_focal"])
def test_llff_bad_pose_row(tmp_path: Path, bad: str) -> None:
    llff_scene(tmp_path)
    arr = np.load(tmp_path / "poses_bounds.npy")
    if bad == "nan_pose":
        arr[2, 3] = np.nan
    elif bad == "scaled_rotation":
        arr[2, [0, 1, 2, 5, 6, 7, 10, 11, 12]] *= 2.0
    else:
        arr[2, 14] = 0.0
    np.save(tmp_path / "poses_bounds.npy", arr)
    with pytest.raises(SceneError, match=r"poses_bounds\.npy row 2"):
        load_scene("llff", tmp_path, "toy", "every_nth")


def test_llff_images_of_different_sizes(tmp_path: Path) -> None:
    llff_scene(tmp_path)
    write_image(tmp_path / "images" / "IMG_3.jpg", 41, 30)
    with pytest.raises(SceneError, match=r"IMG_3\.jpg: image size 41x30"):
        load_scene("llff", tmp_path, "toy", "every_nth")


# ---------------------------------------------------------------- transforms.json

def transforms_frame(gt: GtCam, file_path: str) -> dict:
    T = cam_to_world_matrix(gt)
    T[:3, :3] = T[:3, :3] @ GL_FROM_CV  # OpenCV -> OpenGL camera axes
    return {"file_path": file_path, "transform_matrix": T.tolist()}


def test_transforms_opengl_axes_distortion_and_missing_frame(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    W, H = 48, 32
    dist = (0.05, -0.01, 0.002, -0.001)
    cam = Camera("OPENCV", W, H, (60.0, 62.0, W / 2, H / 2, *dist))
    override = Camera("OPENCV", W, H, (75.0, 75.0, W / 2, H / 2, *dist))
    gts = {f"images/frame_{i:05d}.png": make_gt(30 + i, override if i == 2 else cam) for i in range(1, 5)}
    frames = [transforms_frame(gt, f"./images/frame_{i:05d}" + (".png" if i % 2 else "")) for i, gt in enumerate(gts.values(), 1)]
    frames[1].update(fl_x=75.0, fl_y=75.0)  # nerfstudio per-frame intrinsics
    frames.append(transforms_frame(make_gt(99, cam), "./images/frame_00099.png"))  # listed, not on disk
    for name in gts:
        write_image(tmp_path / name, W, H)
    data = {"fl_x": 60.0, "fl_y": 62.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
            "k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3], "frames": frames,
            "train_filenames": ["images/frame_00001.png", "images/frame_00002.png", "images/frame_00003.png"],
            "test_filenames": ["images/frame_00004.png"]}
    (tmp_path / "transforms.json").write_text(json.dumps(data))

    with caplog.at_level(logging.WARNING):
        scene = load_scene("transforms", tmp_path, "toy")
    assert "1 listed frame(s) missing" in caplog.text and "frame_00099.png" in caplog.text
    assert [f.name for f in scene.frames] == list(gts)
    assert [f.split for f in scene.frames] == ["train", "train", "train", "test"]
    for frame in scene.frames:
        assert frame.camera.model == "OPENCV" and frame.camera.has_distortion
        assert_reprojects(frame, gts[frame.name])

    scene = load_scene("transforms", tmp_path / "transforms.json", "toy", "every_nth", 3)
    assert [f.split for f in scene.frames] == ["test", "train", "train", "test"]


def test_transforms_blender_camera_angle_and_split_files(tmp_path: Path) -> None:
    W = H = 40
    angle = 0.69
    f = 0.5 * W / math.tan(angle / 2)
    cam = Camera("PINHOLE", W, H, (f, f, W / 2, H / 2))
    gts = {}
    for split, n in (("train", 3), ("test", 2)):
        entries = []
        for i in range(n):
            gts[f"{split}/r_{i}.png"] = gt = make_gt(len(gts) + 50, cam)
            write_image(tmp_path / split / f"r_{i}.png", W, H)
            entries.append(transforms_frame(gt, f"./{split}/r_{i}"))
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": entries}))
    scene = load_scene("transforms", tmp_path, "lego")
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"] * 2
    for frame in scene.frames:
        assert frame.camera.model == "PINHOLE"
        assert_reprojects(frame, gts[frame.name])


def test_transforms_given_without_split_is_an_error(tmp_path: Path) -> None:
    write_image(tmp_path / "a.png", 8, 8)
    frame = transforms_frame(make_gt(1, Camera("PINHOLE", 8, 8, (9, 9, 4, 4))), "a.png")
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 9, "w": 8, "h": 8, "frames": [frame]}))
    with pytest.raises(SceneError, match="toy.*train_filenames"):
        load_scene("transforms", tmp_path, "toy")


def test_transforms_all_frames_missing(tmp_path: Path) -> None:
    frame = transforms_frame(make_gt(1, Camera("PINHOLE", 8, 8, (9, 9, 4, 4))), "gone.png")
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 9, "w": 8, "h": 8, "frames": [frame]}))
    with pytest.raises(SceneError, match=r"transforms\.json: none of the 1 listed images exist"):
        load_scene("transforms", tmp_path, "toy", "every_nth")


def test_transforms_unparseable(tmp_path: Path) -> None:
    (tmp_path / "transforms.json").write_text("{ not json")
    with pytest.raises(SceneError, match=r"transforms\.json: unparseable JSON"):
        load_scene("transforms", tmp_path, "toy", "every_nth")


def test_transforms_bad_matrix(tmp_path: Path) -> None:
    write_image(tmp_path / "a.png", 8, 8)
    frames = [{"file_path": "a.png", "transform_matrix": [[1, 0], [0, 1]]}]
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 9, "w": 8, "h": 8, "frames": frames}))
    with pytest.raises(SceneError, match=r"transforms\.json frame 0 \(a\.png\): pose has shape"):
        load_scene("transforms", tmp_path, "toy", "every_nth")


# ---------------------------------------------------------------- COLMAP

def colmap_scene(root: Path, text: bool, model: str = "PINHOLE") -> dict[str, GtCam]:
    """A pycolmap reconstruction written to root/sparse/0 with images in root/images."""
    W, H = 36, 24
    params = {"PINHOLE": [40.0, 41.0, W / 2, H / 2], "SIMPLE_RADIAL": [40.0, W / 2, H / 2, 0.03],
              "OPENCV": [40.0, 41.0, W / 2, H / 2, 0.05, -0.01, 0.002, -0.001],
              "FOV": [40.0, 41.0, W / 2, H / 2, 0.01]}[model]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1))
    fisheye = model == "FOV"  # a model usvc does not import
    cam = Camera("PINHOLE", W, H, tuple(params[:4])) if fisheye else Camera(model, W, H, tuple(params))
    gts = {}
    for image_id, name in enumerate(["frame10.png", "frame2.png", "frame1.png"], start=1):
        gt = make_gt(70 + image_id, cam)
        gts[f"images/{name}"] = gt
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=image_id),
            pycolmap.Rigid3d(pycolmap.Rotation3d(gt.R), gt.t),
        )
        write_image(root / "images" / name, W, H)
        # pycolmap's own projection independently checks this file's projection formula
        if not fisheye:
            np.testing.assert_allclose(rec.image(image_id).project_point(X_WORLD), project(gt.camera, gt.R, gt.t, X_WORLD), atol=1e-9)
    out = root / "sparse" / "0"
    out.mkdir(parents=True)
    rec.write_text(str(out)) if text else rec.write(str(out))
    return gts


@pytest.mark.parametrize("text", [False, True])
def test_colmap_reprojects_binary_and_text(tmp_path: Path, text: bool) -> None:
    gts = colmap_scene(tmp_path, text)
    assert (tmp_path / "sparse/0" / ("cameras.txt" if text else "cameras.bin")).is_file()
    scene = load_scene("colmap", tmp_path, "toy", "every_nth", 2)
    assert [f.name for f in scene.frames] == ["images/frame1.png", "images/frame2.png", "images/frame10.png"]
    assert [f.split for f in scene.frames] == ["test", "train", "test"]
    for frame in scene.frames:
        assert frame.camera.principal_point == (18.0, 12.0)
        assert frame.image_path == tmp_path.resolve() / frame.name
        assert_reprojects(frame, gts[frame.name])
    # the model folder itself is accepted too
    assert len(load_scene("colmap", tmp_path / "sparse" / "0", "toy", "every_nth", 2).frames) == 3


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "OPENCV"])
def test_colmap_distorted_models_pass_through(tmp_path: Path, model: str) -> None:
    gts = colmap_scene(tmp_path, text=False, model=model)
    scene = load_scene("colmap", tmp_path, "toy", "every_nth", 2)
    for frame in scene.frames:
        assert frame.camera.model == model and frame.camera.has_distortion
        assert_reprojects(frame, gts[frame.name])


def test_colmap_unsupported_model(tmp_path: Path) -> None:
    colmap_scene(tmp_path, text=True, model="FOV")
    with pytest.raises(SceneError, match="sparse/0.*unsupported model FOV"):
        load_scene("colmap", tmp_path, "toy", "every_nth", 2)


def test_colmap_given_split_is_an_error(tmp_path: Path) -> None:
    colmap_scene(tmp_path, text=False)
    with pytest.raises(SceneError, match="'toy'.*no train/test split"):
        load_scene("colmap", tmp_path, "toy")


def test_colmap_missing_image(tmp_path: Path) -> None:
    colmap_scene(tmp_path, text=False)
    (tmp_path / "images" / "frame2.png").unlink()
    with pytest.raises(SceneError, match=r"missing image .*images/frame2\.png"):
        load_scene("colmap", tmp_path, "toy", "every_nth", 2)


def test_colmap_unparseable_model(tmp_path: Path) -> None:
    colmap_scene(tmp_path, text=True)
    (tmp_path / "sparse/0/images.txt").write_text("garbage\n1 2 3\n")
    with pytest.raises(SceneError, match="sparse/0: unreadable COLMAP model"):
        load_scene("colmap", tmp_path, "toy", "every_nth", 2)


# ---------------------------------------------------------------- real scene

@pytest.mark.shared
@pytest.mark.skipif(not (SHARED / "scenes" / "office").exists(), reason="needs ../shared/scenes/office")
def test_shared_office_llff() -> None:
    scene = load_scene("llff", SHARED / "scenes" / "office", "office", "every_nth", 8)
    assert len(scene.frames) == 64
    assert len(scene.split("test")) == 8
    for frame in scene.frames:
        check_rotation(frame.R, frame.name)
    centers = np.array([f.center for f in scene.frames])
    forward = np.array([f.R[2] for f in scene.frames])  # camera +z in world coordinates
    # point nearest all optical axes (least squares); every camera must have it in front
    A = sum(np.eye(3) - np.outer(f, f) for f in forward)
    b = sum((np.eye(3) - np.outer(f, f)) @ c for f, c in zip(forward, centers))
    target = np.linalg.solve(A, b)
    to_target = target - centers
    assert np.all(np.einsum("ij,ij->i", to_target, forward) > 0)
    cos = np.einsum("ij,ij->i", to_target / np.linalg.norm(to_target, axis=1, keepdims=True), forward)
    assert np.median(cos) > 0.9
    to_centroid = centers.mean(0) - centers
    assert np.median(np.einsum("ij,ij->i", to_centroid, forward)) > 0
