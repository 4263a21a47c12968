"""The query's features found on a second thread while the network runs: the same keypoints,
matches and answers as found in place."""

from __future__ import annotations

import multiprocessing
import os
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_feature_refinement import synthetic_relocalizer
from test_refinement import CAM, make_map, photo, synthetic_query  # noqa: F401

from usvc.relocalize import query_cores
from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.features.matching import global_match_job, global_matches
from usvc.relocalize.features.sift import feature_job, find_features


def textured(seed: int = 0, shape: tuple[int, int] = (360, 480)) -> np.ndarray:
    """A grey image in [0, 1] of blurred blobs at several scales: something for SIFT to find."""
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for cells in (6, 12, 24):
        small = rng.random((cells * shape[0] // shape[1] + 1, cells)).astype(np.float32)
        img += cv2.resize(small, shape[::-1], interpolation=cv2.INTER_CUBIC)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    return (img - img.min()) / (img.max() - img.min())


def test_features_found_beside_the_network_are_those_found_in_place():
    gray = textured()
    inline = find_features(gray, 240, 2000, "opencv")
    assert inline.resized and min(inline.gray.shape) == 240 and len(inline.feats) > 100
    desc = inline.feats.scaled[::3]  # landmarks that some keypoints match (their bytes, as the landmarks hold them)
    pairs = global_matches(desc, inline.feats, 0.8)
    assert len(pairs[0]) >= 0.9 * len(desc)  # their own keypoints
    for background in (False, True):
        job = feature_job(gray, 240, 2000, "opencv", background=background)
        assert job.background is background
        got = job.result()
        assert got.resized and np.array_equal(got.gray, inline.gray)
        assert np.array_equal(got.feats.uv, inline.feats.uv)
        assert np.array_equal(got.feats.descriptor, inline.feats.descriptor)
        assert job.result() is got  # computed once
        matched = global_match_job(desc, got.feats, 0.8, background=background).result()
        assert all(np.array_equal(a, b) for a, b in zip(matched, pairs))
    small = find_features(gray, 480, 2000, "opencv")
    assert not small.resized and small.gray is gray


def test_a_job_runs_on_the_worker_thread_only_in_the_background(monkeypatch):
    where = []

    def record(*args):
        where.append(threading.current_thread().name)
        return find_features(*args)

    monkeypatch.setattr(sift_module, "find_features", record)
    gray = textured(1, (120, 160))
    feature_job(gray, 240, 500, "opencv", background=True).result()
    lazy = feature_job(gray, 240, 500, "opencv", background=False)
    assert len(where) == 1 and where[0].startswith("usvc-features")
    lazy.result()
    assert where[1] == threading.current_thread().name
    monkeypatch.setattr(query_cores.torch, "get_num_threads", lambda: 1)
    assert not feature_job(gray, 240, 500, "opencv").background  # one thread: in place
    monkeypatch.setattr(query_cores.torch, "get_num_threads", lambda: 2)
    assert feature_job(gray, 240, 500, "opencv").background


def test_the_relocalizer_answers_the_same_with_its_features_found_beside_the_network(
        tmp_path: Path, synthetic_query, monkeypatch):
    reloc, _ = synthetic_relocalizer(tmp_path, monkeypatch)
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    answers = {}
    threads = query_cores.torch.get_num_threads()
    try:
        for background in (False, True):
            monkeypatch.setattr(query_cores.torch, "get_num_threads", lambda b=background: 2 if b else 1)
            answers[background] = [reloc.localize(photo(), intr) for intr in (CAM, None, (2 * fx, 2 * fy, cx, cy))]
    finally:  # the split of a query's threads put back what the patched count said
        query_cores.torch.set_num_threads(threads)
    for a, b in zip(answers[False], answers[True]):
        assert a.success == b.success and a.rejected == b.rejected and a.refine_path == b.refine_path
        assert np.array_equal(a.R, b.R, equal_nan=True) and np.array_equal(a.t, b.t, equal_nan=True)
    assert [a.success for a in answers[True]] == [True, True, False]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_runs_jobs_on_its_own_worker():
    """A child forked after the parent used the worker has none of its threads: its jobs must not
    wait for a worker that does not exist there."""
    gray = textured(2, (120, 160))
    parent = feature_job(gray, 240, 300, "opencv", background=True).result()
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:
        n = pool.apply_async(_child_features, (gray,)).get(timeout=60)
    assert n == len(parent.feats)


def _child_features(gray: np.ndarray) -> int:
    return len(feature_job(gray, 240, 300, "opencv", background=True).result().feats)
