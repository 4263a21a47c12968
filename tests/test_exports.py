"""Exports of localized photos, read back with the tools (and importers) that consume them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.cli.exports import FORMATS, Posed, export, nerfstudio_intrinsics
from usvc.core.errors import UsvcError
from usvc.core.poses_file import read_poses_txt
from usvc.core.scene import Camera
from usvc.prepare.importers import load_scene

W, H = 160, 120
CAMERAS = [
    Camera("SIMPLE_PINHOLE", W, H, (130.0, 80.0, 60.0)),
    Camera("PINHOLE", W, H, (130.0, 125.0, 81.0, 59.0)),
    Camera("OPENCV", W, H, (130.0, 131.0, 80.5, 60.5, 0.05, -0.08, 0.001, -0.002)),
    Camera("SIMPLE_RADIAL", W, H, (128.0, 79.0, 61.0, -0.03)),
    Camera("RADIAL", W, H, (128.0, 79.0, 61.0, -0.03, 0.01)),
    Camera("FULL_OPENCV", W, H, (130.0, 131.0, 80.5, 60.5, 0.05, -0.08, 0.001, -0.002, 0.01, 0, 0, 0)),
]


def posed_photos(folder: Path, cameras: list[Camera]) -> list[Posed]:
    folder.mkdir(parents=True, exist_ok=True)
    items = []
    for i, camera in enumerate(cameras):
        path = folder / f"img{i:02d}.png"
        Image.new("RGB", (camera.width, camera.height)).save(path)
        R = Rotation.random(random_state=i).as_matrix()
        items.append(Posed(str(path), path, camera, R, np.array([0.1 * i, -0.2, 1.5 + i])))
    return items


def records(items: list[Posed]) -> list[dict]:
    return [{"name": i.name, "success": True} for i in items] + [{"name": "failed.png", "success": False}]


def same_projection(a: Camera | pycolmap.Camera, b: Camera | pycolmap.Camera) -> None:
    """Two cameras map the same rays to the same pixels (whatever their model names)."""
    as_colmap = [c if isinstance(c, pycolmap.Camera) else
                 pycolmap.Camera(model=c.model, width=c.width, height=c.height, params=list(c.params)) for c in (a, b)]
    xy = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 7), np.linspace(-0.4, 0.4, 5)), -1).reshape(-1, 2)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    assert (as_colmap[0].width, as_colmap[0].height) == (as_colmap[1].width, as_colmap[1].height)
    np.testing.assert_allclose(as_colmap[0].img_from_cam(rays), as_colmap[1].img_from_cam(rays), atol=1e-9)


@pytest.fixture()
def exported(tmp_path: Path) -> tuple[Path, list[Posed], list[dict]]:
    items = posed_photos(tmp_path / "photos", CAMERAS)
    recs = records(items)
    written = export(tmp_path / "out", FORMATS, recs, items)
    assert sorted(p.name for p in written) == sorted(["queries.jsonl", "poses.txt", "cameras.txt", "images.txt",
                                                      "points3D.txt", "transforms.json"])
    return tmp_path / "out", items, recs


def test_jsonl_and_poses(exported: tuple[Path, list[Posed], list[dict]]) -> None:
    out, items, recs = exported
    assert [json.loads(line) for line in (out / "queries.jsonl").read_text().splitlines()] == recs
    poses = read_poses_txt(out / "poses.txt")
    assert list(poses) == [i.name for i in items]  # the failed photo is only in the JSONL
    for item in items:
        R, t = poses[item.name]
        np.testing.assert_allclose(R, item.R, atol=1e-12)
        np.testing.assert_allclose(t, item.t, atol=1e-12)


def test_colmap_model_loads_in_pycolmap(exported: tuple[Path, list[Posed], list[dict]]) -> None:
    out, items, _ = exported
    rec = pycolmap.Reconstruction(str(out))
    assert rec.num_images() == len(items) and rec.num_points3D() == 0
    assert rec.num_cameras() == len(CAMERAS)
    by_name = {image.name: image for image in rec.images.values()}
    assert sorted(by_name) == sorted(i.path.name for i in items)  # relative to the photos' folder
    for item in items:
        image = by_name[item.path.name]
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        np.testing.assert_allclose(pose.rotation.matrix(), item.R, atol=1e-12)
        np.testing.assert_allclose(pose.translation, item.t, atol=1e-12)
        camera = rec.cameras[image.camera_id]
        assert camera.model.name == item.camera.model
        np.testing.assert_allclose(camera.params, item.camera.params, atol=0)


def test_colmap_shares_identical_cameras_and_names_relative_paths(tmp_path: Path) -> None:
    items = posed_photos(tmp_path / "a", CAMERAS[:1] * 2) + posed_photos(tmp_path / "b", CAMERAS[:1])
    export(tmp_path / "out", ["colmap"], [], items)
    rec = pycolmap.Reconstruction(str(tmp_path / "out"))
    assert rec.num_cameras() == 1
    assert sorted(image.name for image in rec.images.values()) == ["a/img00.png", "a/img01.png", "b/img00.png"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]


ODD_NAMES = ["IMG (1).JPG", "#0012.jpg", "100% done.jpeg", "café ☕.png", "-leading.tif", " lead space.png",
             '"quoted".png', "a\tb.png"]


def test_any_photo_name_round_trips_through_every_format(tmp_path: Path) -> None:
    """Spaces, parentheses, '#', '%', unicode, a leading '-' or space, quotes, tabs: every format
    gives each photo back under its own name (COLMAP's binary model where its text one would cut
    a name at white space; poses.txt quotes a name a reader would misread)."""
    folder = tmp_path / "photos"
    items = []
    for i, (name, camera) in enumerate(zip(ODD_NAMES, CAMERAS + CAMERAS)):
        item = posed_photos(tmp_path / f"src{i}", [camera])[0]
        path = folder / name
        folder.mkdir(exist_ok=True)
        item.path.rename(path)
        items.append(Posed(name, path, camera, item.R, item.t))
    out = tmp_path / "out"
    export(out, FORMATS, records(items), items)
    assert sorted(p.name for p in out.iterdir()) == sorted(["queries.jsonl", "poses.txt", "transforms.json", "cameras.bin",
                                                           "images.bin", "points3D.bin", "rigs.bin", "frames.bin"])
    poses = read_poses_txt(out / "poses.txt")
    assert list(poses) == ODD_NAMES
    rec = pycolmap.Reconstruction(str(out))
    by_name = {image.name: image for image in rec.images.values()}
    assert sorted(by_name) == sorted(ODD_NAMES)
    for item in items:
        np.testing.assert_allclose(poses[item.name][0], item.R, atol=1e-12)
        pose = by_name[item.name].cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), item.R, atol=1e-12)
        np.testing.assert_allclose(pose.translation, item.t, atol=1e-12)
    data = json.loads((out / "transforms.json").read_text(encoding="utf-8"))
    assert [(out / f["file_path"]).resolve() for f in data["frames"]] == [i.path.resolve() for i in items]
    # names without white space keep COLMAP's text model
    plain = [i for i in items if not any(c.isspace() for c in i.name)]
    export(tmp_path / "text", ["colmap"], [], plain)
    assert sorted(p.name for p in (tmp_path / "text").iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    assert sorted(im.name for im in pycolmap.Reconstruction(str(tmp_path / "text")).images.values()) == \
        sorted(i.name for i in plain)


def test_nerfstudio_round_trips_through_the_importer(exported: tuple[Path, list[Posed], list[dict]]) -> None:
    out, items, _ = exported
    data = json.loads((out / "transforms.json").read_text())
    assert data["camera_model"] == "OPENCV" and len(data["frames"]) == len(items)
    for frame, item in zip(data["frames"], items):
        cam_to_world = np.array(frame["transform_matrix"])
        # OpenGL axes: the camera looks down its -z, its y is up; the centre is -R^T t.
        np.testing.assert_allclose(-cam_to_world[:3, 2], item.R[2], atol=1e-12)
        np.testing.assert_allclose(-cam_to_world[:3, 1], item.R[1], atol=1e-12)
        np.testing.assert_allclose(cam_to_world[:3, 3], -item.R.T @ item.t, atol=1e-12)
        assert (frame["w"], frame["h"]) == (W, H) and (out / frame["file_path"]).resolve() == item.path.resolve()
    scene = load_scene("transforms", out, "queries", split_rule="every_nth", split_n=2)
    frames = {Path(f.image_path).name: f for f in scene.frames}
    for item in items:
        frame = frames[item.path.name]
        np.testing.assert_allclose(frame.R, item.R, atol=1e-12)
        np.testing.assert_allclose(frame.t, item.t, atol=1e-12)
        same_projection(frame.camera, item.camera)


def test_nerfstudio_fisheye(tmp_path: Path) -> None:
    fisheye = Camera("OPENCV_FISHEYE", W, H, (100.0, 101.0, 80.0, 60.0, 0.1, -0.02, 0.003, -0.001))
    items = posed_photos(tmp_path / "photos", [fisheye, fisheye])
    export(tmp_path / "out", ["nerfstudio"], [], items)
    assert json.loads((tmp_path / "out" / "transforms.json").read_text())["camera_model"] == "OPENCV_FISHEYE"
    scene = load_scene("transforms", tmp_path / "out", "q", split_rule="every_nth", split_n=2)
    for frame in scene.frames:
        same_projection(frame.camera, fisheye)


def test_nerfstudio_pinhole_has_no_lens_keys() -> None:
    keys = nerfstudio_intrinsics(CAMERAS[1], "x")
    assert keys == {"fl_x": 130.0, "fl_y": 125.0, "cx": 81.0, "cy": 59.0, "w": W, "h": H}
    # An OPENCV camera with zero distortion is a pinhole one.
    assert "camera_model" not in nerfstudio_intrinsics(Camera("OPENCV", W, H, (1, 1, 2, 2, 0, 0, 0, 0)), "x")


@pytest.mark.parametrize("case, formats, cause", [
    ("fisheye-mix", FORMATS, "one lens type"),
    ("rational", ["jsonl", "nerfstudio"], "rational model"),
    ("twice", ["jsonl", "poses"], "given twice"),
    ("format", ["jsonl", "ply"], "unknown --format 'ply'"),
])
def test_failure_writes_nothing(tmp_path: Path, case: str, formats: list[str], cause: str) -> None:
    items = posed_photos(tmp_path / "photos", CAMERAS[:2])
    if case == "fisheye-mix":
        items[1] = Posed(items[1].name, items[1].path, Camera("OPENCV_FISHEYE", W, H, (1, 1, 2, 2, 0.1, 0, 0, 0)),
                         items[1].R, items[1].t)
    elif case == "rational":
        items[1] = Posed(items[1].name, items[1].path, Camera("FULL_OPENCV", W, H, (1, 1, 2, 2, *[0.1] * 8)),
                         items[1].R, items[1].t)
    elif case == "twice":
        items.append(items[0])
    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.txt").write_text("old\n")
    with pytest.raises(UsvcError, match=cause):
        export(out, formats, records(items), items)
    assert sorted(p.name for p in out.iterdir()) == ["poses.txt"] and (out / "poses.txt").read_text() == "old\n"
