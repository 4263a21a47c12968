"""Keyframes of dense posed captures (usvc/sfm/keyframes.py): which frames SfM runs on."""

from __future__ import annotations

import numpy as np
import pytest
from test_sfm import _look_at, small_mini  # noqa: F401 (small_mini: the 24-image prepared scene, a fixture)

from usvc.core.scene import Camera, Frame
from usvc.sfm.keyframes import mapping_keyframes, select_keyframes
from usvc.sfm.options import SfmOptions

CAM = Camera("PINHOLE", 64, 48, (50, 50, 32, 24))


def _orbit(n: int, arc_deg: float, radius: float = 2.0) -> list[Frame]:
    """n cameras on an arc around the origin, each looking at it, named in capture order."""
    frames = []
    for i, a in enumerate(np.radians(np.arange(n) * arc_deg / n)):
        R, t = _look_at(radius * np.array([np.cos(a), np.sin(a), 0.3]), np.zeros(3))
        frames.append(Frame(f"frame-{i:05d}.png", f"frame-{i:05d}.png", CAM, "train", R, t))
    return frames


def test_a_dense_video_keeps_few_keyframes():
    frames = _orbit(1000, 360.0)  # 0.36 degrees and ~0.6 % of the radius per frame
    keep = select_keyframes(frames, 0.04, 2.5)
    assert keep[0]
    assert 60 <= sum(keep) <= 200, sum(keep)
    # kept frames are spread along the whole orbit, not bunched at its start
    idx = np.flatnonzero(keep)
    assert idx[-1] > 950 and np.diff(idx).max() <= 10


def test_a_sparse_capture_keeps_every_frame():
    frames = _orbit(40, 360.0)  # 9 degrees apart
    assert all(select_keyframes(frames, 0.04, 2.5))


def test_zero_thresholds_keep_every_frame():
    frames = _orbit(500, 10.0)
    assert all(select_keyframes(frames, 0.0, 2.5))
    assert all(select_keyframes(frames, 0.04, 0.0))


def test_both_translation_and_rotation_must_be_near():
    # Same orientation, far apart: every frame is kept.
    frames = []
    for i in range(20):
        R, t = _look_at(np.array([float(i), 0.0, 0.0]), np.array([float(i), 5.0, 0.0]))
        frames.append(Frame(f"{i:02d}.png", f"{i:02d}.png", CAM, "train", R, t))
    assert all(select_keyframes(frames, 0.04, 2.5))
    # Same centre, turning 1 degree a frame: a keyframe every 3 frames (2.5 degrees).
    frames = []
    for i in range(30):
        a = np.radians(i)
        R, t = _look_at(np.zeros(3), np.array([np.cos(a), np.sin(a), 0.0]))
        frames.append(Frame(f"{i:02d}.png", f"{i:02d}.png", CAM, "train", R, t))
    # the scale of a capture whose centres coincide is 0: nothing is within 0 x scale, every frame is kept
    assert all(select_keyframes(frames, 0.04, 2.5))
    frames.append(Frame("99.png", "99.png", CAM, "train", *_look_at(np.array([10.0, 0.0, 1.0]), np.zeros(3))))
    keep = select_keyframes(frames, 0.04, 2.5)
    assert np.flatnonzero(keep[:30]).tolist() == list(range(0, 30, 3))


def test_selection_is_deterministic_and_in_name_order():
    frames = _orbit(300, 90.0)
    first = select_keyframes(frames, 0.04, 2.5)
    assert select_keyframes(frames, 0.04, 2.5) == first
    rng = np.random.default_rng(0)
    order = rng.permutation(len(frames))
    shuffled = select_keyframes([frames[i] for i in order], 0.04, 2.5)
    assert [shuffled[k] for k in np.argsort(order)] == first


def test_small_or_unposed_captures_keep_every_frame():
    frames = _orbit(300, 30.0)
    opts = SfmOptions()
    assert len(mapping_keyframes(frames, opts, has_poses=True)) < 200
    assert len(mapping_keyframes(frames, opts, has_poses=False)) == 300
    assert len(mapping_keyframes(frames[:opts.keyframe_min_images], opts, has_poses=True)) == opts.keyframe_min_images
    kept = mapping_keyframes(frames[:opts.keyframe_min_images + 1], opts, has_poses=True)
    assert len(kept) < opts.keyframe_min_images and kept[0] is frames[0]


@pytest.mark.parametrize("field, value", [("keyframe_min_translation", -0.1),
                                          ("keyframe_min_translation", float("nan")),
                                          ("keyframe_min_rotation_deg", -1.0), ("keyframe_min_rotation_deg", 181.0),
                                          ("keyframe_min_rotation_deg", float("nan")), ("keyframe_min_images", -1)])
def test_bad_thresholds_are_refused(field, value):
    problems = SfmOptions(**{field: value}).problems()
    assert len(problems) == 1 and problems[0].startswith(f"{field}=")


def test_defaults_are_valid():
    assert SfmOptions().problems() == []
    assert SfmOptions(keyframe_min_translation=0, keyframe_min_rotation_deg=0, keyframe_min_images=0).problems() == []


@pytest.mark.slow
def test_reconstruct_runs_sfm_on_the_keyframes_only(small_mini, tmp_path):
    import pycolmap

    from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
    from usvc.sfm.reconstruction import reconstruct
    from usvc.sfm.tracks_file import from_reconstruction

    frames = read_scene_h5(small_mini / "scene.h5").split("train")
    assert len(frames) == 24
    # thresholds for this sparse scene (12 frames an arc, ~15 degrees apart): about every other frame
    opts = SfmOptions(keyframe_min_images=0, keyframe_min_translation=0.6, keyframe_min_rotation_deg=40.0,
                      exhaustive_max_images=20, min_points=50)
    keep = select_keyframes(frames, opts.keyframe_min_translation, opts.keyframe_min_rotation_deg)
    expected = sorted(f.name for f, k in zip(frames, keep) if k)
    assert 3 <= len(expected) <= 18
    work = tmp_path / "work"
    work.mkdir()
    rec, info = reconstruct(frames, small_mini / IMAGE_DIR, work, opts, has_poses=True, threads=1)
    assert sorted(im.name for im in rec.images.values()) == expected
    db = pycolmap.Database.open(work / "database.db")
    try:
        assert sorted(im.name for im in db.read_all_images()) == expected  # features of the keyframes only
    finally:
        db.close()
    tracks = from_reconstruction(rec, work / "database.db")
    assert sorted(tracks.image_names) == expected and len(tracks.xyz) >= 50
    # matching=auto goes by the capture's 24 frames (> exhaustive_max_images): pose-guided, not exhaustive
    assert info["mapping_frames"] == 24 and info["matching"] == "poses"
