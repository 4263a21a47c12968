"""Bad images and cameras: oversized headers, 16-bit and float TIFFs, distortion that folds or
keeps little of the photo, pose tables of other photos on small captures, and photo names that
differ between two scenes of one capture. Each gets one clear line (or decodes right)."""

from __future__ import annotations

import logging
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from usvc.core.errors import SceneError, UsvcError
from usvc.core.exif import MAX_IMAGE_PIXELS, apply_orientation, oriented_size
from usvc.core.images import read_image_bgr, read_photo
from usvc.core.scene import Camera, Frame, Scene
from usvc.core.undistort import MIN_KEPT_SIDE, check_distortion, undistorted_camera
from usvc.metrics.alignment import align_and_compare
from usvc.prepare.working_images import prepare_scene
from usvc.sfm.pose_check import pose_agreement, poses_disagree, warn_if_poses_disagree
from usvc.sfm.reconstruction import register_images


# --- 1. a header that claims hundreds of megapixels -------------------------------------------

def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def bomb_png(path: Path, width: int, height: int) -> Path:
    """A PNG of a few hundred bytes whose header claims width x height grey pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * (width + 1) * 4, 9)  # the first rows only
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b""))
    return path


def test_an_image_claiming_more_pixels_than_a_camera_makes_is_refused_from_its_header(tmp_path: Path) -> None:
    png = bomb_png(tmp_path / "huge.png", 20000, 20000)  # over Pillow's own limit too
    assert png.stat().st_size < 100_000 and 20000 * 20000 > MAX_IMAGE_PIXELS
    for read in (read_image_bgr, read_photo, oriented_size):
        with pytest.raises(SceneError, match=r"huge\.png is 20000x20000 = 400 megapixels, more than any camera "
                                             r"makes \(the 250 megapixel limit") as e:
            read(png)
        assert "\n" not in str(e.value)


def test_a_png_over_the_decode_limit_is_refused_in_one_line(tmp_path: Path) -> None:
    png = bomb_png(tmp_path / "big.png", 12000, 10000)  # a camera could make it; its PNG cannot decode reduced
    assert oriented_size(png) == (12000, 10000)
    with pytest.raises(SceneError, match=r"big\.png is 12000x10000 = 120 megapixels, more than the 100 megapixels "
                                         r"decoded in full, and only JPEGs decode reduced"):
        read_photo(png)
    with pytest.raises(SceneError, match=r"more than the 100 megapixels decoded in full, downscale it"):
        read_image_bgr(png)


@pytest.mark.parametrize("limit, reduction", [(10**9, 1), (320 * 240 - 1, 2), (320 * 240 // 4 - 1, 4),
                                              (320 * 240 // 16 - 1, 8)])
def test_a_jpeg_over_the_decode_limit_is_decoded_reduced_and_says_by_how_much(tmp_path: Path, monkeypatch, limit,
                                                                               reduction) -> None:
    from usvc.core import images

    bgr = cv2.resize(np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8), (320, 240))
    jpg = tmp_path / "big.jpg"
    cv2.imwrite(str(jpg), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    monkeypatch.setattr(images, "MAX_DECODE_PIXELS", limit)
    found = read_photo(jpg)
    assert found.reduction == reduction and found.size == (320, 240)
    assert found.bgr.shape == (240 // reduction, 320 // reduction, 3) and found.scale() == (1 / reduction,) * 2
    expected = cv2.resize(bgr, (320 // reduction, 240 // reduction), interpolation=cv2.INTER_AREA)
    assert np.abs(found.bgr.astype(int) - expected).mean() < 4  # the same picture, smaller
    if reduction > 1:
        with pytest.raises(SceneError, match="read it with read_photo"):
            read_image_bgr(jpg)
    monkeypatch.setattr(images, "MAX_DECODE_PIXELS", 320 * 240 // 64 - 1)
    with pytest.raises(SceneError, match="even reduced 8 times"):
        read_photo(jpg)


def test_a_turned_jpeg_over_the_limit_is_turned_and_reduced(tmp_path: Path, monkeypatch) -> None:
    from usvc.core import images

    stored = cv2.resize(np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8), (320, 240))
    jpg = tmp_path / "portrait.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored[..., ::-1]).save(jpg, quality=95, exif=exif)
    monkeypatch.setattr(images, "MAX_DECODE_PIXELS", 320 * 240 - 1)
    found = read_photo(jpg)
    assert found.size == (240, 320) and found.bgr.shape == (160, 120, 3) and found.reduction == 2
    monkeypatch.setattr(images, "MAX_DECODE_PIXELS", 10**9)
    full = read_photo(jpg).bgr
    half = cv2.resize(full, (120, 160), interpolation=cv2.INTER_AREA)
    assert np.abs(found.bgr.astype(int) - half).mean() < 4


def test_an_image_under_the_limit_still_decodes(tmp_path: Path) -> None:
    png = tmp_path / "ok.png"
    cv2.imwrite(str(png), np.full((30, 40, 3), 77, np.uint8))
    assert read_image_bgr(png).shape == (30, 40, 3) and oriented_size(png) == (40, 30)


# --- 2. 16-bit and floating-point TIFFs ---------------------------------------------------------

REF = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)  # BGR, 8 bits


@pytest.mark.parametrize("kind", ["uint16 colour", "uint16 grey", "float32 colour", "float32 grey",
                                  "float64 grey", "uint16 colour png"])
def test_wide_samples_decode_to_the_8_bit_pixels(tmp_path: Path, kind: str) -> None:
    grey = "grey" in kind
    ref = np.repeat(REF[..., :1], 3, axis=2) if grey else REF
    pixels = REF[..., 0] if grey else REF
    if kind.startswith("uint16"):
        # off the multiples of 257 (but not past 65535), so the rounding is exercised
        stored = pixels.astype(np.uint16) * 257 + (pixels < 255).astype(np.uint16) * 100
    else:
        stored = pixels.astype(kind.split()[0]) / 255
    path = tmp_path / ("img.png" if kind.endswith("png") else "img.tif")
    assert cv2.imwrite(str(path), stored)
    out = read_image_bgr(path)
    assert out.dtype == np.uint8 and out.shape == ref.shape
    assert np.abs(out.astype(int) - ref.astype(int)).max() <= 1, "16-bit must not read as white, 0..1 floats not black"


@pytest.mark.parametrize("orientation", [3, 6, 8])
@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
def test_a_turned_grey_tiff_is_turned_and_scaled(tmp_path: Path, orientation: int, dtype: str) -> None:
    """Pillow 13 decodes grey TIFFs with orientation 5-8 into a turned frame (garbage) unless told otherwise."""
    path = tmp_path / "turned.tif"
    exif = Image.Exif()
    exif[0x0112] = orientation
    grey = REF[..., 0]
    stored = {"uint8": grey, "uint16": grey.astype(np.uint16) * 257, "float32": grey.astype(np.float32) / 255}[dtype]
    Image.fromarray(stored).save(path, exif=exif)
    out = read_image_bgr(path)
    expected = apply_orientation(grey, orientation)
    assert out.shape[:2] == expected.shape and oriented_size(path) == expected.shape[::-1]
    assert np.abs(out[..., 0].astype(int) - expected.astype(int)).max() <= 1


@pytest.mark.parametrize(("pixels", "why"), [
    (REF.astype(np.float32), r"float32 pixels range 0\.\.25\d, but floating-point photos are read as 0\.\.1"),
    (np.where(REF > 128, np.nan, REF / 255).astype(np.float32), "float32 pixels include NaN or infinity"),
    (REF[..., 0].astype(np.int32) * 1000, r"int32 samples \(32-bit integer\) are not supported"),
])
def test_samples_that_cannot_be_scaled_are_refused_by_name(tmp_path: Path, pixels: np.ndarray, why: str) -> None:
    path = tmp_path / "data.tif"
    assert cv2.imwrite(str(path), pixels)
    with pytest.raises(SceneError, match=rf"image .*data\.tif: {why}"):
        read_image_bgr(path)


# --- 3. distortion that folds over, or keeps little of the photo ---------------------------------

W, H = 640, 360


@pytest.mark.parametrize("camera", [
    Camera("SIMPLE_RADIAL", W, H, (500.0, 320.0, 180.0, -5.0)),
    Camera("OPENCV_FISHEYE", W, H, (500.0, 500.0, 320.0, 180.0, -5.0, 0.0, 0.0, 0.0)),
    Camera("OPENCV", W, H, (300.0, 300.0, 320.0, 180.0, -0.3, 0.0, 0.0, 0.0)),  # folds at 211 of 320 px
])
def test_distortion_that_folds_over_is_refused_naming_the_camera(camera: Camera) -> None:
    params = ", ".join(f"{v:g}" for v in camera.params)
    for fov in ("crop", "full"):
        with pytest.raises(SceneError, match=rf"camera {camera.model} 640x360 \(params {params}\): its lens "
                                             r"distortion folds over: .* cannot be undistorted"):
            undistorted_camera(camera, fov)


@pytest.mark.parametrize("camera", [
    Camera("SIMPLE_RADIAL", W, H, (400.0, 320.0, 180.0, 5.0)),
    Camera("OPENCV_FISHEYE", W, H, (400.0, 400.0, 320.0, 180.0, 5.0, 0.0, 0.0, 0.0)),
])
def test_distortion_that_keeps_little_of_the_photo_is_warned_about(camera: Camera, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="usvc"):
        pinhole = undistorted_camera(camera)
        undistorted_camera(camera)  # once per camera
    assert min(pinhole.width / W, pinhole.height / H) < MIN_KEPT_SIDE
    warnings = [r.getMessage() for r in caplog.records if "keeps a" in r.getMessage()]
    assert len(warnings) == 1
    assert f"camera {camera.model} 640x360" in warnings[0] and f"keeps a {pinhole.width}x{pinhole.height}" in warnings[0]


def test_a_fold_in_the_outermost_corner_is_only_warned_about(caplog) -> None:
    camera = Camera("SIMPLE_RADIAL", W, H, (500.0, 320.0, 180.0, -0.31))  # turns back 94 % of the way to the corner
    with caplog.at_level(logging.WARNING, logger="usvc"):
        undistorted_camera(camera)
    assert "the outermost corner cannot be undistorted" in caplog.text


@pytest.mark.parametrize("camera", [
    Camera("SIMPLE_RADIAL", W, H, (500.0, 320.0, 180.0, -0.08)),
    Camera("RADIAL", W, H, (500.0, 320.0, 180.0, -0.08, 0.03)),
    Camera("OPENCV", W, H, (500.0, 500.0, 320.0, 180.0, 0.058, -0.081, 0.001, -0.002)),
    Camera("OPENCV_FISHEYE", W, H, (300.0, 300.0, 320.0, 180.0, 0.05, -0.02, 0.0, 0.0)),
    Camera("OPENCV_FISHEYE", W, H, (150.0, 150.0, 320.0, 180.0, 0.0, 0.0, 0.0, 0.0)),  # 100 degrees to the corner
])
def test_ordinary_lenses_pass_quietly(camera: Camera, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="usvc"):
        for fov in ("crop", "full"):
            check_distortion(camera, fov)
    assert not caplog.records


def test_prepare_refuses_a_folding_camera_before_writing_anything(tmp_path: Path) -> None:
    camera = Camera("SIMPLE_RADIAL", 64, 48, (50.0, 32.0, 24.0, -5.0))
    frames = []
    for i in range(3):
        path = tmp_path / "raw" / f"{i}.png"
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), np.full((48, 64, 3), 60 * i, np.uint8))
        frames.append(Frame(f"{i}.png", path, camera, "train" if i else "test", np.eye(3), np.array([0.1 * i, 0, 0])))
    out = tmp_path / "prepared"
    out.mkdir()
    with pytest.raises(SceneError, match=r"camera SIMPLE_RADIAL 64x48 \(params 50, 32, 24, -5\) of 0\.png and 2 more "
                                         r"photos: its lens distortion folds over"):
        prepare_scene(Scene("folded", frames, 1.0, tmp_path / "raw"), out, working_width=0)
    assert not any(out.iterdir())


# --- 4. pose rows of other photos on a small capture ---------------------------------------------

def forward_capture(tmp: Path, n: int = 12, size: tuple[int, int] = (480, 360), seed: int = 0,
                    spacing: float = 0.1) -> tuple[Path, list[Frame]]:
    """A forward-facing (LLFF-like) capture of n cameras on a 4x3 grid `spacing` m apart, 3-7 m from
    the points, written into a COLMAP database as keypoints (0.5 px noise) and verified matches."""
    rng = np.random.default_rng(seed)
    w, h = size
    cam = Camera("PINHOLE", w, h, (w * 0.83, w * 0.83, w / 2, h / 2))
    X = np.c_[rng.uniform(-2.5, 2.5, 600), rng.uniform(-1.8, 1.8, 600), rng.uniform(3.0, 7.0, 600)]
    frames = []
    for i in range(n):
        c = spacing * np.array([i % 4, i // 4, 0.0]) + rng.normal(0, 0.1 * spacing, 3)
        R = Rotation.from_rotvec(np.radians(rng.normal(0, 0.2, 3))).as_matrix()
        frames.append(Frame(f"{i:03d}.png", tmp / f"{i:03d}.png", cam, "train", R, -R @ c))
    db_path = tmp / "database.db"
    register_images(frames, db_path)
    db = pycolmap.Database.open(db_path)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        seen = []
        for f in frames:
            x = (X @ f.R.T + f.t) @ cam.K.T
            uv = x[:, :2] / x[:, 2:] + rng.normal(0, 0.5, (len(X), 2))
            db.write_keypoints(ids[f.name], uv.astype(np.float32))
            seen.append((uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h))
        for i in range(n):
            for j in range(i + 1, n):
                common = np.flatnonzero(seen[i] & seen[j])
                geometry = pycolmap.TwoViewGeometry()
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                geometry.inlier_matches = np.c_[common, common].astype(np.uint32)
                db.write_two_view_geometry(ids[frames[i].name], ids[frames[j].name], geometry)
    finally:
        db.close()
    return db_path, frames


def test_shuffled_pose_rows_on_a_small_capture_are_reported(tmp_path: Path, caplog) -> None:
    db, frames = forward_capture(tmp_path)
    right = pose_agreement(db, frames)
    assert right["pairs"] == 66 and right["pairs_disagreeing"] == 0 and right["median_pair_epipolar_px"] < 1.0
    assert right["pair_threshold_px"] == pytest.approx(6.0)  # 8 px at 640 px, scaled to 480 px
    assert not poses_disagree(right) and not warn_if_poses_disagree(right)
    perm = np.random.default_rng(0).permutation(len(frames))
    shuffled = [replace(f, R=frames[k].R, t=frames[k].t) for f, k in zip(frames, perm)]
    wrong = pose_agreement(db, shuffled)
    # small views close together: the median pair stays under the old fixed 8 px, though many pairs disagree
    assert wrong["median_pair_epipolar_px"] < 8.0 and wrong["pairs_disagreeing"] > wrong["pairs"] / 4
    with caplog.at_level(logging.WARNING, logger="usvc"):
        assert warn_if_poses_disagree(wrong)
    assert "another order than the images" in caplog.text and "6.0 px" in caplog.text


@pytest.mark.parametrize("a, b", [(0, 19), (1, 18), (5, 6)])
def test_one_swapped_pair_of_poses_is_named(tmp_path: Path, caplog, a: int, b: int) -> None:
    """Two photos' poses swapped on a 20-photo capture (0.3 m grid, 3-7 m from the scene): too few
    pairs for the whole-capture rule, but most of those two photos' own pairs disagree, by several
    thresholds, and they are named."""
    db, frames = forward_capture(tmp_path, n=20, spacing=0.3)
    assert pose_agreement(db, frames)["suspect_images"] == {}
    swapped = list(frames)
    swapped[a], swapped[b] = (replace(frames[a], R=frames[b].R, t=frames[b].t),
                              replace(frames[b], R=frames[a].R, t=frames[a].t))
    stats = pose_agreement(db, swapped)
    assert not poses_disagree(stats)
    assert sorted(stats["suspect_images"]) == [f"{a:03d}.png", f"{b:03d}.png"]
    with caplog.at_level(logging.WARNING, logger="usvc"):
        assert warn_if_poses_disagree(stats)
    assert f"{a:03d}.png (" in caplog.text and f"{b:03d}.png (" in caplog.text and "swapped" in caplog.text


def test_a_photo_whose_pairs_disagree_only_a_little_is_not_named(tmp_path: Path) -> None:
    """Poses swapped between the far corners of a 0.1 m grid (0.5 m apart) move the epipolar lines by
    about one threshold: as much as a loosely registered photo of a right capture (bird's worst), so
    no photo is named."""
    db, frames = forward_capture(tmp_path, n=20, spacing=0.1)
    swapped = list(frames)
    swapped[0], swapped[19] = replace(frames[0], R=frames[19].R, t=frames[19].t), replace(frames[19], R=frames[0].R,
                                                                                          t=frames[0].t)
    stats = pose_agreement(db, swapped)
    assert stats["pairs_disagreeing"] > 0 and stats["suspect_images"] == {}


def test_larger_images_get_a_larger_pair_threshold(tmp_path: Path) -> None:
    db, frames = forward_capture(tmp_path, size=(960, 720), seed=1)
    right = pose_agreement(db, frames)
    assert right["pair_threshold_px"] == pytest.approx(12.0) and not poses_disagree(right)
    perm = np.random.default_rng(0).permutation(len(frames))
    wrong = pose_agreement(db, [replace(f, R=frames[k].R, t=frames[k].t) for f, k in zip(frames, perm)])
    assert poses_disagree(wrong) and wrong["worst_images"]


# --- 5. two scenes of one capture that name the photos differently -------------------------------

@pytest.fixture(scope="module")
def sfm_posing(tmp_path_factory):
    from benchmarks.accuracy import sfm_posing

    return sfm_posing


def _posed(names: list[str], scale: float = 1.0) -> list[Frame]:
    cam = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    rng = np.random.default_rng(3)
    out = []
    for name in names:
        R = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        out.append(Frame(name, Path(name), cam, "train", R, scale * rng.normal(0, 1, 3)))
    return out


def test_sfm_posing_matches_photos_by_file_name(sfm_posing) -> None:
    given = _posed([f"images/{i:04d}.jpg" for i in range(5)])
    sfm = [replace(f, name=Path(f.name).name) for f in _posed([f"images/{i:04d}.jpg" for i in range(5)], 2.0)]
    with pytest.raises(UsvcError, match="at least 3 shared posed photos, got 0"):
        align_and_compare(sfm, given)  # what the benchmark did before matching
    names, how = sfm_posing.match_photos(given, sfm)
    assert how == "file name" and names == {f"{i:04d}.jpg": f"images/{i:04d}.jpg" for i in range(5)}
    errors = align_and_compare([replace(f, name=names[f.name]) for f in sfm], given)
    assert len(errors.names) == 5
    assert sfm_posing.match_photos(given, given[:3]) == ({f.name: f.name for f in given[:3]}, "name")


def test_sfm_posing_refuses_ambiguous_or_unshared_file_names(sfm_posing) -> None:
    given = _posed(["a/0000.jpg", "b/0000.jpg", "a/0001.jpg", "a/0002.jpg"])
    sfm = _posed(["0000.jpg", "0001.jpg", "0002.jpg"])
    with pytest.raises(UsvcError, match=r"the given scene has two photos named '0000\.jpg' \(a/0000\.jpg and "
                                        r"b/0000\.jpg\): cannot match"):
        sfm_posing.match_photos(given, sfm)
    names, _ = sfm_posing.match_photos(given, sfm[1:])  # the ambiguous name is not needed: no error
    assert names == {"0001.jpg": "a/0001.jpg", "0002.jpg": "a/0002.jpg"}
    with pytest.raises(UsvcError, match="share no photo by name or file name"):
        sfm_posing.match_photos(given, _posed(["x.jpg", "y.jpg", "z.jpg"]))
