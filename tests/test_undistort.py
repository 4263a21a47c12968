"""Lens undistortion: COLMAP camera models -> PINHOLE, checked geometrically and photometrically,
through `prepare` and on a distorted copy of a real scene."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pycolmap
import pytest
from conftest import REPO, shared_scene

from usvc.analysis.distorted_scene import (
    DistortOptions,
    distorted_camera,
    undistortion_psnr,
    write_distorted_scene,
)
from usvc.core.errors import SceneError
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.scene_file import read_scene_h5
from usvc.core.undistort import (
    distort_pinhole,
    resample,
    to_pycolmap,
    undistort,
    undistorted_camera,
    valid_mask,
)
from usvc.prepare.importers import load_scene
from usvc.prepare.working_images import prepare_scene

PINHOLE = Camera("PINHOLE", 160, 120, (150.0, 150.0, 80.0, 60.0))
DISTORTED = {
    "SIMPLE_RADIAL": (-0.08,),
    "RADIAL": (-0.08, 0.03),
    "OPENCV": (0.058, -0.081, 0.001, -0.002),
    "FULL_OPENCV": (0.05, -0.08, 0.001, -0.001, 0.01, 0.0, 0.0, 0.0),
    "OPENCV_FISHEYE": (0.05, -0.02, 0.0, 0.0),
}


def texture(width: int = 160, height: int = 120, seed: int = 0) -> np.ndarray:
    """Smooth colour texture (band-limited, so bilinear resampling twice loses little)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC), (0, 0), 2.0)


def test_pinhole_passes_through_untouched() -> None:
    image = texture()
    out, cam = undistort(image, PINHOLE)
    assert out is image and cam == PINHOLE
    simple = Camera("SIMPLE_PINHOLE", 160, 120, (150.0, 80.0, 60.0))
    assert undistorted_camera(simple) == Camera("PINHOLE", 160, 120, (150.0, 150.0, 80.0, 60.0))


@pytest.mark.parametrize("model", sorted(DISTORTED))
def test_round_trip_recovers_the_pinhole_view(model: str) -> None:
    """Distort a pinhole image with a known model, undistort it: the original's view comes back."""
    image = texture()
    cam = distorted_camera(PINHOLE, model, DISTORTED[model])
    psnr, valid = undistortion_psnr(image, PINHOLE, distort_pinhole(image, PINHOLE, cam), cam)
    assert valid > 0.95
    assert psnr > 35.0


@pytest.mark.parametrize("model", sorted(DISTORTED))
def test_crop_has_no_blank_pixels_and_full_keeps_every_pixel(model: str) -> None:
    cam = distorted_camera(PINHOLE, model, DISTORTED[model])
    crop, full = undistorted_camera(cam, "crop"), undistorted_camera(cam, "full")
    assert crop.model == full.model == "PINHOLE"
    assert valid_mask(cam, crop).all()  # every output pixel has data
    assert full.width * full.height >= crop.width * crop.height
    # every source pixel lands inside the "full" view: project the source border through it
    u = np.concatenate([np.linspace(0.5, 159.5, 50), np.full(50, 0.5), np.linspace(0.5, 159.5, 50), np.full(50, 159.5)])
    v = np.concatenate([np.full(50, 0.5), np.linspace(0.5, 119.5, 50), np.full(50, 119.5), np.linspace(0.5, 119.5, 50)])
    rays = to_pycolmap(cam).cam_from_img(np.stack([u, v], 1))
    (fx, fy), (cx, cy) = full.focal, full.principal_point
    x, y = rays[:, 0] * fx + cx, rays[:, 1] * fy + cy
    assert x.min() > -1.0 and y.min() > -1.0 and x.max() < full.width + 1 and y.max() < full.height + 1


def test_opencv_model_matches_opencv_projection() -> None:
    """The resampling map agrees with OpenCV's own distortion model (an independent implementation),
    so an OPENCV camera from nerfstudio means what OpenCV means by it."""
    params = (150.0, 148.0, 81.0, 59.0, 0.058, -0.081, 0.001, -0.002)
    cam = Camera("OPENCV", 160, 120, params)
    pinhole = undistorted_camera(cam)
    map_x = resample(np.tile(np.arange(160, dtype=np.float32), (120, 1)), cam, pinhole)
    map_y = resample(np.tile(np.arange(120, dtype=np.float32)[:, None], (1, 160)), cam, pinhole)
    assert map_x.shape == (pinhole.height, pinhole.width)
    v, u = np.mgrid[10:pinhole.height - 10:7, 10:pinhole.width - 10:7]
    (fx, fy), (cx, cy) = pinhole.focal, pinhole.principal_point
    rays = np.stack([(u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, np.ones(u.shape)], -1).reshape(-1, 1, 3)
    K = np.array([[150.0, 0, 80.5], [0, 148.0, 58.5], [0, 0, 1]])  # OpenCV: pixel centres on integers
    proj, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.array(params[4:]))
    proj = proj.reshape(u.shape + (2,))
    np.testing.assert_allclose(map_x[v, u], proj[..., 0], atol=1e-2)
    np.testing.assert_allclose(map_y[v, u], proj[..., 1], atol=1e-2)


def test_wrong_image_size_is_one_clear_error() -> None:
    with pytest.raises(SceneError, match="photo.jpg: image is 100x120 but its camera says 160x120"):
        undistort(np.zeros((120, 100, 3), np.uint8), PINHOLE, where="photo.jpg")
    with pytest.raises(SceneError, match="not one of"):
        undistorted_camera(distorted_camera(PINHOLE, "OPENCV", DISTORTED["OPENCV"]), "wide")


def _pinhole_scene(root: Path, n: int = 6) -> Scene:
    root.mkdir(parents=True)
    frames = []
    for i in range(n):
        path = root / f"img_{i}.png"
        cv2.imwrite(str(path), texture(seed=i))
        angle = 0.1 * i
        R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        frames.append(Frame(f"img_{i}.png", path, PINHOLE, "test" if i % 3 == 0 else "train", R, np.array([0.1 * i, 0, 0])))
    return Scene("toy", frames, None, root)


@pytest.mark.parametrize("fmt,model", [("transforms", "OPENCV"), ("transforms", "OPENCV_FISHEYE"),
                                       ("colmap", "SIMPLE_RADIAL"), ("colmap", "RADIAL")])
def test_prepare_undistorts_every_format(tmp_path: Path, fmt: str, model: str) -> None:
    """A distorted scene written as transforms.json or a COLMAP model: prepare writes PINHOLE
    cameras and undistorted images, keeps the poses, and records the source camera."""
    src = _pinhole_scene(tmp_path / "src")
    out = tmp_path / "distorted"
    out.mkdir()
    info = write_distorted_scene(src, out, DistortOptions(model, fmt))
    scene = load_scene(fmt, out, "toy", "every_nth", 3)
    assert {f.camera.model for f in scene.frames} == {model}
    prepared = tmp_path / "prepared"
    prepared.mkdir()
    stats = prepare_scene(scene, prepared, working_width=0)
    assert stats["undistorted"] == 6 and stats["source_camera_models"] == [model]
    back = read_scene_h5(prepared / "scene.h5")
    assert {f.camera.model for f in back.frames} == {"PINHOLE"}
    with h5py.File(prepared / "scene.h5") as h5:  # the imported cameras, kept beside the pinhole ones
        assert list(h5["source_camera_model"].asstr()[()]) == [model] * 6
    by_name = {f.name: f for f in src.frames}
    source_of = {Path(new).name: old for old, new in info["names"].items()}
    for frame in back.frames:
        original = by_name[source_of[Path(frame.name).name]]
        np.testing.assert_allclose(frame.R, original.R, atol=1e-9)
        np.testing.assert_allclose(frame.t, original.t, atol=1e-9)
        image = cv2.imread(str(frame.image_path))
        assert image.shape[:2] == (frame.camera.height, frame.camera.width)
        reference = resample(cv2.imread(str(original.image_path)), PINHOLE, frame.camera)
        valid = valid_mask(PINHOLE, frame.camera)
        mse = np.mean((image.astype(float) - reference.astype(float))[valid] ** 2)
        assert 10 * np.log10(255**2 / mse) > 30.0, frame.name  # JPEG q95 + two resamplings
    assert info["frames"] == 6


def test_transforms_camera_errors(tmp_path: Path) -> None:
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(tmp_path / name), texture())
    cam_to_world = np.eye(4).tolist()

    def write(**intr: object) -> None:
        frames = [{"file_path": name, "transform_matrix": cam_to_world} for name in ("a.png", "b.png")]
        (tmp_path / "transforms.json").write_text(json.dumps({"w": 160, "h": 120, "fl_x": 150, **intr, "frames": frames}))
    write(camera_model="EQUIRECTANGULAR")
    with pytest.raises(SceneError, match="transforms.json frame 0 .*camera model 'EQUIRECTANGULAR' is not supported"):
        load_scene("transforms", tmp_path, "toy", "every_nth", 2)
    write(camera_model="OPENCV_FISHEYE", k1=0.1, p1=0.01)
    with pytest.raises(SceneError, match="OPENCV_FISHEYE has no tangential terms"):
        load_scene("transforms", tmp_path, "toy", "every_nth", 2)
    write(camera_model="OPENCV", k1=0.1, k3=0.02)
    assert load_scene("transforms", tmp_path, "toy", "every_nth", 2).frames[0].camera.model == "FULL_OPENCV"
    write(w=100, camera_model="OPENCV", k1=0.1)  # the camera says 100 px wide, the image is 160
    scene = load_scene("transforms", tmp_path, "toy", "every_nth", 2)
    (tmp_path / "prepared").mkdir()
    with pytest.raises(SceneError, match=r"[ab]\.png: image is 160x120 but its camera says 100x120"):
        prepare_scene(scene, tmp_path / "prepared", 0)


def test_camera_parameter_count_is_checked() -> None:
    with pytest.raises(SceneError, match="OPENCV takes 8 parameters, got 6"):
        Camera("OPENCV", 160, 120, (150.0, 150.0, 80.0, 60.0, 0.1, 0.0))
    with pytest.raises(SceneError, match="unknown camera model 'FOV'"):
        Camera("FOV", 160, 120, (150.0, 150.0, 80.0, 60.0, 0.1))


@pytest.mark.shared
@pytest.mark.slow
def test_distorted_office_round_trip(tmp_path: Path) -> None:
    """The script that makes the distorted office variants; undistortion gives back the originals
    (PSNR over the valid region, JPEG re-encoding included), and prepare runs on the result."""
    office = shared_scene("office")
    out = tmp_path / "office_radial"
    proc = subprocess.run([sys.executable, "scripts/make_distorted_scene.py", "--src", str(office),
                           "--model", "SIMPLE_RADIAL", "--format", "colmap", "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["frames"] == 64 and report["model"] == "SIMPLE_RADIAL"
    assert report["psnr_db_min"] > 40.0 and report["valid_fraction_mean"] > 0.99
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == 64
