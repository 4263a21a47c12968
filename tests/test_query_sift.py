"""Where a query's SIFT runs (`relocalize.features_extractor`, usvc/relocalize/features/sift.py):
`auto` is COLMAP's SIFT on the relocalizer's GPU where pycolmap was built with CUDA, OpenCV's on
the CPU everywhere else; COLMAP's GPU extractor is asked for with that GPU's index and an image
bound that holds the photo. The GPU itself is exercised by the `cuda` test at the end."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from test_feature_refinement import synthetic_relocalizer
from test_refinement import CAM, photo, synthetic_query  # noqa: F401

from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.features.sift import SiftChoice, choose_sift, extract_sift
from usvc.relocalize.options import RelocalizeOptions


def blocks(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """A uint8 grey image of random 4 px blocks: corners SIFT finds."""
    rng = np.random.default_rng(seed)
    img = (rng.random((shape[0] // 4 + 1, shape[1] // 4 + 1)) * 255).astype(np.uint8)
    return np.ascontiguousarray(np.kron(img, np.ones((4, 4), np.uint8))[: shape[0], : shape[1]])


@pytest.mark.parametrize("setting", ["auto", "opencv", "colmap"])
@pytest.mark.parametrize("cuda", [False, True])
def test_on_the_cpu_the_sift_is_where_it_always_was(setting: str, cuda: bool, monkeypatch):
    """On a CPU relocalizer `auto` is OpenCV's SIFT, as `opencv`; `colmap` is COLMAP's on the CPU,
    whatever pycolmap could do on a GPU."""
    monkeypatch.setattr(sift_module, "pycolmap_has_cuda", lambda: cuda)
    expected = {"auto": SiftChoice("opencv"), "opencv": SiftChoice("opencv"), "colmap": SiftChoice("colmap")}
    assert choose_sift(setting, "cpu") == expected[setting]


def test_on_a_gpu_auto_is_colmaps_sift_on_that_gpu_where_pycolmap_has_cuda(monkeypatch):
    monkeypatch.setattr(sift_module, "pycolmap_has_cuda", lambda: True)
    monkeypatch.setattr(sift_module, "_gpu_sift_problem", lambda gpu: "")  # its extractor starts there
    assert choose_sift("auto", "cuda") == SiftChoice("colmap", 0)
    assert choose_sift("auto", "cuda:1") == SiftChoice("colmap", 1)
    assert choose_sift("colmap", "cuda:2") == SiftChoice("colmap", 2)
    assert choose_sift("opencv", "cuda:1") == SiftChoice("opencv")  # asked for by name: the CPU's
    assert str(choose_sift("auto", "cuda:1")) == "colmap (cuda:1)"


def test_on_a_gpu_without_pycolmaps_cuda_the_sift_stays_on_the_cpu_and_says_so(monkeypatch, caplog):
    monkeypatch.setattr(sift_module, "pycolmap_has_cuda", lambda: False)
    with caplog.at_level(logging.INFO, logger=sift_module.__name__):
        assert choose_sift("auto", "cuda") == SiftChoice("opencv")
        assert choose_sift("colmap", "cuda:0") == SiftChoice("colmap")
    assert "no CUDA" in caplog.text and "pycolmap-cuda12" in caplog.text


def test_a_gpu_where_colmaps_sift_does_not_start_leaves_the_sift_on_the_cpu(monkeypatch, caplog):
    """pycolmap-cuda12 on a machine whose GPU SiftGPU cannot use (it then falls back to OpenGL and
    fails): one warning naming why, and the CPU's SIFT, not a failure inside every query."""
    monkeypatch.setattr(sift_module, "pycolmap_has_cuda", lambda: True)
    sift_module._extractor.cache_clear()
    sift_module._gpu_sift_problem.cache_clear()

    def create(options, device):
        if device == pycolmap.Device.cuda:
            raise ValueError("[extraction.cc:50] 'FeatureExtractor::Create(*options)' Must be non NULL")
        raise AssertionError("only the GPU extractor is tried")

    monkeypatch.setattr(pycolmap.FeatureExtractor, "create", create)
    try:
        with caplog.at_level(logging.WARNING, logger=sift_module.__name__):
            assert choose_sift("auto", "cuda:0") == SiftChoice("opencv")
            assert choose_sift("colmap", "cuda:0") == SiftChoice("colmap")
    finally:
        sift_module._extractor.cache_clear()
        sift_module._gpu_sift_problem.cache_clear()
    assert "does not start on cuda:0" in caplog.text and "Must be non NULL" in caplog.text


def test_an_unknown_extractor_is_named():
    with pytest.raises(ValueError, match="features_extractor='sift-gpu'"):
        choose_sift("sift-gpu", "cpu")
    problems = RelocalizeOptions(features_extractor="sift-gpu").problems()
    assert len(problems) == 1 and "auto" in problems[0] and "colmap" in problems[0]


def test_colmaps_gpu_extractor_is_asked_for_on_that_gpu_with_room_for_the_photo(monkeypatch):
    """The GPU extractor gets use_gpu, the GPU's index, COLMAP's detector settings and a size bound
    that holds the photo; its features come back as the CPU path's (unit rows, COLMAP pixels)."""
    made = []
    cpu = sift_module._extractor(500)  # COLMAP's CPU extractor stands in for the GPU's

    def create(options, device):
        made.append((options.use_gpu, options.gpu_index, options.max_image_size, options.sift.first_octave,
                     options.sift.max_num_features, device))
        return cpu

    sift_module._extractor.cache_clear()
    monkeypatch.setattr(pycolmap.FeatureExtractor, "create", create)
    try:
        gray = blocks((300, 1100))
        on_gpu = extract_sift(gray, 500, SiftChoice("colmap", 1))
        again = extract_sift(gray, 500, SiftChoice("colmap", 1))  # the extractor is made once
    finally:
        sift_module._extractor.cache_clear()
    assert made == [(True, "1", 2048, sift_module.FIRST_OCTAVE, 500, pycolmap.Device.cuda)]
    on_cpu = extract_sift(gray, 500, "colmap")
    assert len(on_gpu) > 50 and np.array_equal(on_gpu.uv, on_cpu.uv) and np.array_equal(again.uv, on_cpu.uv)
    assert np.allclose(np.linalg.norm(on_gpu.descriptor, axis=1), 1.0, atol=1e-3)
    with pytest.raises(ValueError, match="unknown SIFT extractor"):
        extract_sift(gray, 500, SiftChoice("opencv", 0))  # OpenCV's SIFT has no GPU here


def test_the_relocalizer_finds_the_query_features_with_its_choice(tmp_path: Path, synthetic_query, monkeypatch):
    """Relocalizer(device=...) chooses once, and every photo's features come from that choice."""
    reloc, feats = synthetic_relocalizer(tmp_path, monkeypatch)
    assert reloc.sift == SiftChoice("opencv")  # the default, `auto`, on the CPU
    seen = []

    def sift(gray, n, extractor):
        seen.append(extractor)
        return feats

    monkeypatch.setattr(sift_module, "extract_sift", sift)
    reloc.sift = SiftChoice("colmap", 3)  # as chosen on a GPU machine
    assert reloc.localize(photo(), CAM).success
    assert seen == [SiftChoice("colmap", 3)]


@pytest.mark.parametrize("extractor", ["opencv", "colmap"])
def test_sift_extractors_give_unit_descriptors_in_colmap_pixels(extractor: str):
    rng = np.random.default_rng(0)
    img = (rng.random((120, 160)) * 255).astype(np.uint8)
    img = np.kron(img[::4, ::4], np.ones((4, 4), np.uint8))[:120, :160]  # blocks: corners SIFT finds
    feats = extract_sift(img, 500, extractor)
    assert len(feats) > 20 and feats.descriptor.dtype == np.float32
    assert np.allclose(np.linalg.norm(feats.descriptor, axis=1), 1.0, atol=1e-3)
    assert np.all(feats.descriptor >= 0)
    assert np.all((feats.uv >= 0) & (feats.uv <= [160, 120]))


def cv2_blur(small: np.ndarray) -> np.ndarray:
    """A 240 x 320 image of smooth blobs: SIFT's kind of structure, at several scales."""
    big = cv2.resize(small, (320, 240), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(big, (0, 0), 1.5)


def test_opencv_sift_finds_colmaps_keypoints_where_colmap_finds_them():
    """OpenCV's SIFT with COLMAP's detector settings (precise upscaling, COLMAP's peak threshold)
    lands on COLMAP's own keypoints: OpenCV's default upscaling shifts them by a quarter pixel,
    which guided matching turns into pose error."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    img = cv2_blur((rng.random((60, 80)) * 255).astype(np.uint8))
    colmap, opencv = extract_sift(img, 2000, "colmap"), extract_sift(img, 2000, "opencv")
    assert len(opencv) >= 0.7 * len(colmap) > 50
    dist, nearest = cKDTree(opencv.uv).query(colmap.uv)
    near = dist < 1.0
    assert near.mean() > 0.6
    offset = opencv.uv[nearest[near]] - colmap.uv[near]
    assert np.all(np.abs(np.median(offset, axis=0)) < 0.02)  # the default upscaling: ~0.24 px on each axis
    agree = np.einsum("ij,ij->i", opencv.descriptor[nearest[near]], colmap.descriptor[near])
    assert np.median(agree) > 0.95


def test_opencv_sift_gives_the_same_keypoints_in_the_same_order_whatever_its_threads():
    """Same config, same bits: OpenCV's SIFT runs parallel loops, and its keypoints (order included,
    which guided matching's ties follow) must not depend on how many threads it had."""
    img = cv2_blur((np.random.default_rng(2).random((60, 80)) * 255).astype(np.uint8))
    before = cv2.getNumThreads()
    try:
        runs = []
        for n in (1, 2, 4):
            cv2.setNumThreads(n)
            runs.append(extract_sift(img, 2000, "opencv"))
    finally:
        cv2.setNumThreads(before)
    assert len(runs[0]) > 50
    for other in runs[1:]:
        assert np.array_equal(other.uv, runs[0].uv) and np.array_equal(other.descriptor, runs[0].descriptor)


@pytest.mark.cuda
@pytest.mark.skipif(not sift_module.pycolmap_has_cuda(), reason="pycolmap without CUDA (pycolmap-cuda12)")
def test_colmaps_sift_on_the_gpu_finds_the_cpus_keypoints():
    """On a GPU (pycolmap-cuda12): COLMAP's GPU SIFT finds most of its CPU SIFT's keypoints at the
    same places, with descriptors that match them (SiftGPU is not the same code, so not the same bits)."""
    gray = cv2_blur((np.random.default_rng(1).random((60, 80)) * 255).astype(np.uint8))
    gpu, cpu = extract_sift(gray, 2000, SiftChoice("colmap", 0)), extract_sift(gray, 2000, "colmap")
    assert len(gpu) >= 0.7 * len(cpu)
    d = np.linalg.norm(cpu.uv[:, None] - gpu.uv[None], axis=2)
    near = d.min(axis=1) < 1.0
    assert near.mean() > 0.6
    same = (cpu.descriptor[near] * gpu.descriptor[d[near].argmin(axis=1)]).sum(axis=1)
    assert np.median(same) > 0.9
