"""The sfm stage's SIFT with OpenCV (`sfm.extractor=opencv`): COLMAP's database form, the same rows
on any thread count, the query's own features, and a model as good as COLMAP's extraction gives."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from test_sfm import OPTS, small_mini  # noqa: F401  (the 24-image miniature scene fixture)

from usvc.core import opencv_sift
from usvc.core.scene_file import IMAGE_DIR, read_scene_h5
from usvc.landmarks.landmark_table import unit_descriptors
from usvc.relocalize.features.sift import extract_sift
from usvc.sfm.opencv_extraction import image_features, write_opencv_features
from usvc.sfm.options import SfmOptions
from usvc.sfm.reconstruction import reconstruct, register_images


def _rows(db_path, names):
    db = pycolmap.Database.open(db_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        return [(np.asarray(db.read_keypoints(ids[n])), np.asarray(db.read_descriptors(ids[n]).data)) for n in names]
    finally:
        db.close()


def test_opencv_features_go_into_the_database_in_colmaps_form_on_any_thread_count(small_mini, tmp_path):  # noqa: F811
    frames = read_scene_h5(small_mini / "scene.h5").split("train")[:6]
    names = sorted(f.name for f in frames)
    rows = []
    for threads in (1, 2, 3):
        db_path = tmp_path / f"{threads}.db"
        register_images(frames, db_path)
        total = write_opencv_features(db_path, small_mini / IMAGE_DIR, names, 4096, threads)
        rows.append(_rows(db_path, names))
        assert total == sum(len(k) for k, _ in rows[-1]) > 6 * 200
    for other in rows[1:]:  # the same bits whatever the thread count
        for (ka, da), (kb, db_) in zip(rows[0], other):
            np.testing.assert_array_equal(ka, kb)
            np.testing.assert_array_equal(da, db_)
    keypoints, descriptors = rows[0][0]
    assert keypoints.shape[1] in (4, 6) and descriptors.dtype == np.uint8 and descriptors.shape[1] == 128
    direct_kp, direct_desc = image_features(small_mini / IMAGE_DIR / names[0], 4096)
    np.testing.assert_allclose(keypoints[:, :2], direct_kp[:, :2], atol=1e-4)  # x, y in COLMAP's convention
    np.testing.assert_array_equal(descriptors, direct_desc)


def test_colmaps_uint8_encoding_keeps_the_querys_descriptors(small_mini):  # noqa: F811
    import cv2

    name = sorted(f.name for f in read_scene_h5(small_mini / "scene.h5").split("train"))[0]
    gray = cv2.cvtColor(cv2.imread(str(small_mini / IMAGE_DIR / name)), cv2.COLOR_BGR2GRAY)
    query = extract_sift(gray, 4096, "opencv")
    keypoints, unit = opencv_sift.detect(gray, 4096)
    np.testing.assert_array_equal(query.uv, opencv_sift.colmap_uv(keypoints))
    stored = unit_descriptors(opencv_sift.colmap_descriptors(unit))
    cosine = np.einsum("ij,ij->i", stored, query.descriptor)
    assert len(cosine) > 200 and cosine.min() > 0.995  # 8-bit rounding only: the landmarks match the query's own
    # the keypoint rows: x, y as the query's, then COLMAP's scale (sigma) and orientation (radians)
    rows = opencv_sift.colmap_keypoints(keypoints)
    np.testing.assert_allclose(rows[:, :2], query.uv, atol=1e-4)
    assert np.all(rows[:, 2] > 0) and np.all(np.abs(rows[:, 3]) <= 2 * np.pi)


@pytest.mark.slow
def test_opencv_extraction_maps_the_miniature_scene_as_colmaps_does(small_mini, tmp_path):  # noqa: F811
    frames = read_scene_h5(small_mini / "scene.h5").split("train")
    stats = {}
    for extractor in ("colmap", "opencv"):
        work = tmp_path / extractor
        work.mkdir()
        opts = SfmOptions(**{**OPTS.__dict__, "extractor": extractor})
        rec, info = reconstruct(frames, small_mini / IMAGE_DIR, work, opts, has_poses=True, threads=2)
        errors = [p.error for p in rec.points3D.values()]
        stats[extractor] = (len(rec.points3D), float(np.median(errors)))
    (n_colmap, err_colmap), (n_opencv, err_opencv) = stats["colmap"], stats["opencv"]
    assert n_opencv >= 0.8 * n_colmap > 400
    assert err_opencv < max(1.5 * err_colmap, 0.3)


def test_an_unknown_extractor_is_named():
    problems = SfmOptions(extractor="sift-gpu").problems()
    assert any("extractor" in p and "colmap" in p and "opencv" in p for p in problems)
