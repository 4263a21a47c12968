"""Unposed photos (``images`` format): import, SfM posing in prepare, and the pose comparison."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_scene
from scipy.spatial.transform import Rotation
from test_exif import photo

from usvc.core.errors import SceneError, SfmError, UsvcError
from usvc.core.scene import Camera, Frame
from usvc.core.scene_file import read_scene_h5
from usvc.metrics.alignment import align_and_compare
from usvc.prepare.importers import load_scene
from usvc.prepare.working_images import prepare_scene
from usvc.sfm.reconstruction import SfmOptions

OPTS = SfmOptions(max_num_features=4096, matching="auto", exhaustive_max_images=150, sequential_overlap=10,
                  pose_pairs_per_image=20, reconstruction="auto", min_points=100, num_threads=-1, seed=0)


def test_images_format_reads_exif_focal_and_falls_back_to_a_guess(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    photo(tmp_path / "images" / "a.jpg", size=(80, 60), **{"a405": 28})  # FocalLengthIn35mmFilm
    photo(tmp_path / "images" / "b.jpg", size=(80, 60))
    photo(tmp_path / "images" / "c.png", orientation=6, size=(80, 60))  # turned: 60 x 80 upright
    scene = load_scene("images", tmp_path, "photos", "every_nth", 3)
    assert [f.name for f in scene.frames] == ["images/a.jpg", "images/b.jpg", "images/c.png"]
    assert not scene.has_poses
    assert [f.split for f in scene.frames] == ["test", "train", "train"]
    a, b, c = scene.frames
    assert a.camera.model == "SIMPLE_RADIAL" and a.focal_known
    assert a.camera.params[0] == pytest.approx(28 / 36 * 80, rel=1e-6)
    assert a.camera.params[1:] == (40.0, 30.0, 0.0)
    assert not b.focal_known and b.camera.params[0] == pytest.approx(1.2 * 80)
    assert (c.camera.width, c.camera.height) == (60, 80)


def test_images_format_without_photos_is_one_clear_error(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("no photos here")
    with pytest.raises(SceneError, match=r"scene 'photos': no photos .* in "):
        load_scene("images", tmp_path, "photos", "every_nth", 8)


def test_photos_that_cannot_be_posed_are_a_clear_error(tmp_path: Path) -> None:
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((60, 80, 3), 90 + i, np.uint8))
    scene = load_scene("images", tmp_path, "blank", "every_nth", 4)
    out = tmp_path / "prepared"
    out.mkdir()
    with pytest.raises(SfmError, match="scene 'blank': COLMAP could not initialise a reconstruction"):
        prepare_scene(scene, out, working_width=0, sfm=OPTS, threads=-1)
    assert not any(out.iterdir())
    with pytest.raises(SceneError, match="has no poses: preparing it needs SfM options"):
        prepare_scene(scene, out, working_width=0)


def _frames(centres: np.ndarray, rotations: np.ndarray) -> list[Frame]:
    cam = Camera("PINHOLE", 64, 48, (50, 50, 32, 24))
    return [Frame(f"{i}.png", f"{i}.png", cam, "train", R, -R @ c) for i, (c, R) in enumerate(zip(centres, rotations))]


def test_alignment_undoes_a_similarity_and_measures_what_is_left() -> None:
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(10, 3))
    rots = Rotation.random(10, random_state=1).as_matrix()
    ref = _frames(centres, rots)
    S = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    scale, shift = 0.37, np.array([1.0, -2.0, 0.5])
    # the same cameras in another frame: x_est = scale * S x_ref + shift
    est = _frames(scale * centres @ S.T + shift, rots @ S.T)
    errors = align_and_compare(est, ref)
    assert errors.scale == pytest.approx(1 / scale, rel=1e-9)
    assert errors.rotation_deg.max() < 1e-5 and errors.center_error.max() < 1e-9
    # one camera moved and turned after the fit: its errors show, fitted on the others
    moved = est[:9] + [Frame("9.png", "9.png", est[9].camera, "train",
                             Rotation.from_euler("z", 2, degrees=True).as_matrix() @ est[9].R,
                             -(Rotation.from_euler("z", 2, degrees=True).as_matrix() @ est[9].R)
                             @ (est[9].center + np.array([0.037, 0, 0])))]
    errors = align_and_compare(moved, ref, fit_on={f"{i}.png" for i in range(9)})
    assert errors.rotation_deg[9] == pytest.approx(2.0, abs=1e-6)
    assert errors.center_error[9] == pytest.approx(0.037 / scale, rel=1e-6)
    assert errors.center_error[:9].max() < 1e-9
    with pytest.raises(UsvcError, match="at least 3 shared posed photos"):
        align_and_compare(est[:2], ref)


def _check_posed(prepared: Path, given: list[Frame], stats: dict, rot_deg: float, centre_frac: float) -> None:
    posed = read_scene_h5(prepared / "scene.h5")
    assert posed.pose_source == "sfm" and stats["pose_source"] == "sfm"
    assert {f.camera.model for f in posed.frames} == {"PINHOLE"}
    mapping = {f.name for f in posed.frames if f.split == "train"}
    errors = align_and_compare(posed.frames, given, fit_on=mapping)
    queries = [i for i, n in enumerate(errors.names) if n not in mapping]
    assert queries, "the queries must be posed too"
    assert np.median(errors.rotation_deg) < rot_deg and errors.rotation_deg[queries].max() < 2 * rot_deg
    assert np.median(errors.center_error) < centre_frac * errors.extent
    assert errors.center_error[queries].max() < 3 * centre_frac * errors.extent


@pytest.mark.slow
def test_unposed_miniature_photos_get_the_true_poses_up_to_a_similarity(tmp_path: Path) -> None:
    from usvc.generate.params import RoomParams
    from usvc.generate.writer import generate_scene

    raw = tmp_path / "raw"
    generate_scene(raw, RoomParams(frames_per_map_sequence=12, n_query_frames=2, supersample=1))
    truth = tmp_path / "truth"
    truth.mkdir()
    prepare_scene(load_scene("ace", raw, "mini", "given"), truth, working_width=0)
    given = read_scene_h5(truth / "scene.h5").frames
    photos = tmp_path / "photos"
    photos.mkdir()
    for f in given:  # the same photos, flat, with nothing but pixels
        shutil.copy(f.image_path, photos / Path(f.name).name.replace("/", "_"))
    scene = load_scene("images", photos, "mini_photos", "every_nth", 6)
    out = tmp_path / "posed"
    out.mkdir()
    stats = prepare_scene(scene, out, working_width=0, sfm=OPTS, threads=-1)
    assert stats["frames"] + len(stats["unposed"]) == len(given)
    assert stats["frames"] >= 0.9 * len(given)
    renamed = [Frame(Path(f.name).name, f.image_path, f.camera, f.split, f.R, f.t) for f in given]
    _check_posed(out, renamed, stats, rot_deg=1.0, centre_frac=0.02)


@pytest.mark.slow
@pytest.mark.shared
def test_unposed_office_photos_match_the_given_poses(tmp_path: Path) -> None:
    """The office capture's photos alone: SfM poses agree with the capture's own (COLMAP) poses."""
    root = shared_scene("office")
    given_dir = tmp_path / "given"
    given_dir.mkdir()
    prepare_scene(load_scene("llff", root, "office", "every_nth", 8), given_dir, working_width=640)
    photos = tmp_path / "photos"
    shutil.copytree(root / "images", photos / "images")
    out = tmp_path / "posed"
    out.mkdir()
    stats = prepare_scene(load_scene("images", photos, "office_photos", "every_nth", 8), out, 640, sfm=OPTS, threads=-1)
    assert stats["frames"] == 64 and not stats["unposed"]
    assert stats["sfm_cameras"][0]["model"] == "SIMPLE_RADIAL"
    _check_posed(out, read_scene_h5(given_dir / "scene.h5").frames, stats, rot_deg=1.0, centre_frac=0.02)


def test_a_corrupt_photo_in_an_images_scene_is_named_and_nothing_is_written(tmp_path: Path) -> None:
    for i in range(3):
        photo(tmp_path / f"{i}.jpg", size=(80, 60))
    data = (tmp_path / "1.jpg").read_bytes()
    (tmp_path / "1.jpg").write_bytes(data[: len(data) // 2])
    scene = load_scene("images", tmp_path, "photos", "every_nth", 3)
    out = tmp_path / "prepared"
    out.mkdir()
    with pytest.raises(SceneError, match=r"1\.jpg: truncated or corrupt JPEG"):
        prepare_scene(scene, out, working_width=0, sfm=OPTS, threads=-1)
    assert not any(out.iterdir())


def test_similarity_maps_poses_into_the_reference_frame() -> None:
    """A pose of the estimate's frame, mapped by the fitted similarity, is the reference pose."""
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(8, 3))
    rots = Rotation.random(8, random_state=4).as_matrix()
    ref = _frames(centres, rots)
    S = Rotation.from_euler("zyx", [10, 70, -30], degrees=True).as_matrix()
    est = _frames(2.5 * centres @ S.T + [0.3, 0.1, -4.0], rots @ S.T)
    sim = align_and_compare(est, ref).similarity
    for e, r in zip(est, ref):
        R, t = sim.pose(e.R, e.t)
        np.testing.assert_allclose(R, r.R, atol=1e-9)
        np.testing.assert_allclose(t, r.t, atol=1e-9)
