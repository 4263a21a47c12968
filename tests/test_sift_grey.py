"""Every SIFT in usvc sees the grey COLMAP's image reader makes (usvc/core/sift_grey.py): the
landmarks' SIFT ran on it, so a query's keypoints and descriptors are the landmarks' kind only if
the query's SIFT runs on it too."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from test_feature_refinement import synthetic_relocalizer
from test_refinement import CAM, photo, synthetic_query  # noqa: F401

from usvc.core.sift_grey import colmap_grey
from usvc.model.preprocess import luma01
from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.features.sift import SiftChoice, choose_sift


def every_colour() -> np.ndarray:
    """A 4096 x 4096 RGB image holding each of the 16.7 M colours once."""
    levels = np.arange(256, dtype=np.uint8)
    r, g, b = np.meshgrid(levels, levels, levels, indexing="ij")
    return np.stack([r, g, b], axis=-1).reshape(4096, 4096, 3)


def colmaps(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(pycolmap.Bitmap.from_array(np.ascontiguousarray(rgb)).clone_as_grey().to_array()).reshape(
        rgb.shape[:2])


def test_the_grey_is_colmaps_on_every_colour_ties_included():
    rgb = every_colour()
    expected = colmaps(rgb)
    assert np.array_equal(colmap_grey(rgb, rgb=True), expected)
    assert np.array_equal(colmap_grey(np.ascontiguousarray(rgb[..., ::-1]), rgb=False), expected)  # BGR, as cv2 reads
    # the network's luma (Rec. 601) is another grey on most colours: what the query's SIFT used to see
    assert (np.rint(luma01(rgb, rgb=True) * 255).astype(np.uint8) != expected).mean() > 0.5


def test_a_grey_image_is_its_own_grey_and_other_input_is_refused():
    grey = np.random.default_rng(0).integers(0, 256, (30, 40), dtype=np.uint8)
    assert np.array_equal(colmap_grey(grey, rgb=True), grey)
    with pytest.raises(ValueError, match="uint8"):
        colmap_grey(grey.astype(np.float32), rgb=True)
    with pytest.raises(ValueError, match="HxWx3"):
        colmap_grey(np.zeros((4, 4, 4), np.uint8), rgb=True)


def test_the_grey_of_a_photo_file_is_the_one_colmaps_reader_gives_its_sift(tmp_path: Path):
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    path = tmp_path / "photo.png"
    cv2.imwrite(str(path), rgb[..., ::-1])
    read = np.asarray(pycolmap.Bitmap.read(str(path), as_rgb=False).to_array()).reshape(48, 64)
    assert np.array_equal(colmap_grey(cv2.imread(str(path)), rgb=False), read)


@pytest.mark.parametrize("channels", ["rgb", "bgr"])
@pytest.mark.parametrize("extractor", ["colmap", "opencv"])
def test_the_relocalizers_sift_sees_the_grey_its_mapping_twin_saw(tmp_path: Path, synthetic_query, monkeypatch,
                                                                  channels: str, extractor: str):
    """COLMAP's SIFT on COLMAP's grey (as the sfm stage's SIFT read the mapping photos), OpenCV's on
    the network's luma (as `sfm.extractor=opencv` converts them); the network's input is the luma."""
    reloc, feats = synthetic_relocalizer(tmp_path, monkeypatch)
    reloc.sift = SiftChoice(extractor)
    seen = []
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: seen.append(gray) or feats)
    networked = []
    scene_coordinates = type(reloc).scene_coordinates
    monkeypatch.setattr(type(reloc), "scene_coordinates",
                        lambda self, g: networked.append(g) or scene_coordinates(self, g))
    image = photo()  # 160 x 120, the map's short side: neither image is resized
    assert reloc.localize(image, CAM, channels=channels).success
    luma = luma01(image, rgb=channels == "rgb")
    expected = colmap_grey(image, rgb=channels == "rgb") if extractor == "colmap" \
        else np.clip(np.rint(luma * 255.0), 0, 255).astype(np.uint8)
    assert len(seen) == 1 and seen[0].dtype == np.uint8 and np.array_equal(seen[0], expected)
    assert np.array_equal(networked[0], luma)


def test_with_prior_none_auto_is_sift_and_pnps_own_sift():
    assert choose_sift("auto", "cpu", "none") == SiftChoice("colmap")
    assert choose_sift("auto", "cpu", "learned") == SiftChoice("opencv")
    assert choose_sift("opencv", "cpu", "none") == SiftChoice("opencv")  # asked for by name: kept
