"""The two threads of a query split the cores: the network on torch's share, every BLAS product on
the side's share, the side work's SIFT on all of them (it outlasts the network), and every pool as
it was once the query is done."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_feature_refinement import synthetic_relocalizer
from test_refinement import CAM, H_CELLS, R_TRUE, SMALL_BIAS, T_TRUE, W_CELLS, coordinate_map, photo
from threadpoolctl import threadpool_info

from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.query_cores import side_libraries, split
from usvc.relocalize.relocalizer import Relocalizer


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


@pytest.fixture
def pools():
    """torch's and OpenCV's pools put back as they were after the test, whatever it set."""
    before = torch.get_num_threads(), cv2.getNumThreads()
    yield
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])


@pytest.mark.parametrize("threads,want", [(1, (1, 1)), (2, (1, 1)), (3, (2, 1)), (4, (2, 2)), (16, (8, 8))])
def test_the_threads_are_split_between_the_network_and_the_side_work(threads: int, want: tuple[int, int]):
    assert split(threads) == want


def test_a_query_runs_each_side_on_its_own_share_and_leaves_the_pools_as_they_were(tmp_path: Path, monkeypatch,
                                                                                    pools):
    reloc, feats = synthetic_relocalizer(tmp_path, monkeypatch)
    seen: dict[str, list] = {"network": [], "sift": []}
    forward, network_of = reloc.regressor.forward, Relocalizer.scene_coordinates
    coords = coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS).reshape(H_CELLS, W_CELLS, 3)

    def network(*args):
        seen["network"].append((threading.current_thread().name, torch.get_num_threads()))
        return forward(*args)

    def synthetic(self, gray):  # the map's network runs (its thread count is what is seen), the
        network_of(self, gray)  # coordinates are the synthetic query's
        return coords

    def sift(gray, n, extractor):
        seen["sift"].append((threading.current_thread().name, cv2.getNumThreads(), _blas_threads()))
        return feats

    monkeypatch.setattr(reloc.regressor, "forward", network)
    monkeypatch.setattr(Relocalizer, "scene_coordinates", synthetic)
    monkeypatch.setattr(sift_module, "extract_sift", sift)
    torch.set_num_threads(2)
    cv2.setNumThreads(3)
    blas = _blas_threads()
    alone = None
    for threads in (2, 1):
        torch.set_num_threads(threads)
        answer = reloc.localize(photo(), CAM)
        assert answer.success and answer.refine_path == "guided"
        if alone is None:
            alone = answer
        assert np.array_equal(answer.R, alone.R) and np.array_equal(answer.t, alone.t)
        assert (torch.get_num_threads(), cv2.getNumThreads(), _blas_threads()) == (threads, 3, blas)
    (main, torch_two), (_, torch_one) = seen["network"]
    (worker, cv_two, blas_two), (inline, cv_one, blas_one) = seen["sift"]
    # OpenCV's SIFT on both threads (it outlasts the network), BLAS on the side's one
    assert torch_two == 1 and worker.startswith("usvc-features") and cv_two == 2 and set(blas_two) <= {1}
    # with one thread the side work runs in place, and nothing is split
    assert torch_one == 1 and inline == main and cv_one == 3 and blas_one == blas


def test_overlapping_queries_put_the_pools_back_once_the_last_one_leaves(pools):
    cv2.setNumThreads(3)
    blas = _blas_threads()
    first, second = side_libraries(1), side_libraries(1)
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    assert cv2.getNumThreads() == 1 and set(_blas_threads()) <= {1}  # the second query still runs
    second.__exit__(None, None, None)
    assert cv2.getNumThreads() == 3 and _blas_threads() == blas


def test_a_batch_of_queries_sets_blas_with_torch_and_opencv(pools):
    from usvc.relocalize.photo_batch import query_threads

    torch.set_num_threads(2)
    cv2.setNumThreads(3)
    blas = _blas_threads()
    with query_threads(1):
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (1, 1) and set(_blas_threads()) <= {1}
    assert (torch.get_num_threads(), cv2.getNumThreads(), _blas_threads()) == (2, 3, blas)
