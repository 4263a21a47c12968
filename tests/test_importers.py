"""Importers: each fixture is written in the format's exact published layout from known
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
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.errors import SceneError, UsvcError
from usvc.importers import FORMATS, load_scene
from usvc.scene import Camera, Frame, check_rotation

SHARED = Path(__file__).resolve().parents[2] / "shared"
X_WORLD = np.array([0.3, -0.2, 1.7])
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


@dataclass
class GtCam:
    """Ground truth: world-to-camera R, t (OpenCV axes) and a COLMAP-convention camera."""

    R: np.ndarray
    t: np.ndarray
    camera: Camera

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def R_c2w(self) -> np.ndarray:
        return self.R.T


def make_gt(seed: int, camera: Camera, depth: float = 4.0) -> GtCam:
    """A random rotation placed so X_WORLD lies in front of the camera, off the optical axis."""
    R = Rotation.random(random_state=seed).as_matrix()
    rng = np.random.default_rng(seed)
    p_cam = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), 1.0]) * depth
    center = X_WORLD - R.T @ p_cam
    return GtCam(R=R, t=-R @ center, camera=camera)


def project(camera: Camera, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """COLMAP's projection for the models the importers produce (distortion included)."""
    x, y, z = R @ X + t
    assert z > 0
    x, y = x / z, y / z
    p = camera.params
    if camera.model == "SIMPLE_RADIAL":
        scale = 1 + p[3] * (x * x + y * y)
        x, y = x * scale, y * scale
    elif camera.model == "OPENCV":
        k1, k2, p1, p2 = p[4:]
        r2 = x * x + y * y
        radial = k1 * r2 + k2 * r2 * r2
        dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        x, y = x + dx, y + dy
    elif camera.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise AssertionError(f"test projection does not cover {camera.model}")
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    return np.array([fx * x + cx, fy * y + cy])


def assert_reprojects(frame: Frame, gt: GtCam) -> None:
    expected = project(gt.camera, gt.R, gt.t, X_WORLD)
    got = project(frame.camera, frame.R, frame.t, X_WORLD)
    np.testing.assert_allclose(got, expected, atol=1e-6, err_msg=frame.name)
    assert (frame.camera.width, frame.camera.height) == (gt.camera.width, gt.camera.height)


def write_image(path: Path, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (width, height), (120, 60, 30)).save(path)


def write_pose_txt(path: Path, T: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in T) + "\n")


def c2w_matrix(gt: GtCam) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = gt.R_c2w, gt.center
    return T


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
        Rc = gt.R_c2w  # columns right, down, forward
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
    T = c2w_matrix(gt)
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
              "OPENCV_FISHEYE": [40.0, 41.0, W / 2, H / 2, 0, 0, 0, 0]}[model]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1))
    fisheye = model == "OPENCV_FISHEYE"
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
    colmap_scene(tmp_path, text=True, model="OPENCV_FISHEYE")
    with pytest.raises(SceneError, match="sparse/0.*unsupported model OPENCV_FISHEYE"):
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
            write_pose_txt(root / split / "poses" / f"{stem}.pose.txt", c2w_matrix(gt))
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
            write_pose_txt(root / f"{name}.pose.txt", c2w_matrix(gt))
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
    llff_scene(tmp_path)
    with pytest.raises(SceneError, match="split rule 'random'"):
        load_scene("llff", tmp_path, "toy", "random")
    with pytest.raises(SceneError, match="n >= 2"):
        load_scene("llff", tmp_path, "toy", "every_nth", 1)


def test_errors_are_usvc_errors() -> None:
    assert issubclass(SceneError, UsvcError)


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
