"""Guided matching by tiles of the image (`usvc.relocalize.features.tiled_matching`) against its definition:
one landmarks x keypoints product with the radius as a mask."""

from __future__ import annotations

import numpy as np
import pytest

from usvc.relocalize.features import tiled_matching
from usvc.relocalize.features.tiled_matching import row_best_two_within, tiles_pay


def _unit(a: np.ndarray) -> np.ndarray:
    return (a / np.linalg.norm(a, axis=1, keepdims=True)).astype(np.float32)


def _definition(lm_uv, lm_desc, kp_uv, kp_desc, radius):
    sim = lm_desc @ kp_desc.T
    d2 = ((lm_uv[:, None, :] - kp_uv[None, :, :]) ** 2).sum(axis=2)
    sim = np.where(d2 <= radius * radius, sim, -np.inf).astype(np.float32)
    first = np.argmax(sim, axis=1)
    s1 = sim[np.arange(len(sim)), first]
    sim[np.arange(len(sim)), first] = -np.inf
    s2 = sim.max(axis=1)
    first[~np.isfinite(s1)] = 0
    return first, s1, s2


def _points(seed: int, n_lm: int = 400, n_kp: int = 700, w: float = 320.0, h: float = 240.0):
    rng = np.random.default_rng(seed)
    lm_uv = rng.uniform([0, 0], [w, h], (n_lm, 2))
    kp_uv = np.concatenate([rng.uniform([0, 0], [w, h], (n_kp - 100, 2)),
                            rng.normal([40, 40], 5.0, (100, 2))])  # a cluster: many keypoints in one tile
    lm_desc = _unit(rng.normal(size=(n_lm, 128)))
    kp_desc = _unit(rng.normal(size=(n_kp, 128)))
    return lm_uv, lm_desc, kp_uv, kp_desc


@pytest.mark.parametrize("max_tiles", [1, 12, 48, 10_000])
@pytest.mark.parametrize("radius", [0.5, 3.0, 17.0, 60.0, 500.0])
def test_tiles_give_the_masked_product(radius: float, max_tiles: int, monkeypatch):
    """Whatever the tiles' width (one tile for everything, or tiles as wide as the radius, with
    a cluster of keypoints in one), each landmark's best keypoint and two similarities are those
    of the full product with the radius as a mask."""
    monkeypatch.setattr(tiled_matching, "MAX_TILES", max_tiles)
    lm_uv, lm_desc, kp_uv, kp_desc = _points(int(radius * 10) + max_tiles)
    got = row_best_two_within(lm_uv, lm_desc, kp_uv, kp_desc, radius)
    want = _definition(lm_uv, lm_desc, kp_uv, kp_desc, radius)
    assert np.array_equal(got[0], want[0])
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=1e-6)
    assert np.array_equal(np.isfinite(got[1]), np.isfinite(want[1]))
    assert np.array_equal(np.isfinite(got[2]), np.isfinite(want[2]))


def test_ties_go_to_the_first_keypoint_and_the_radius_is_inclusive():
    lm_uv = np.array([[50.0, 50.0], [200.0, 100.0], [5.0, 5.0]])
    lm_desc = _unit(np.eye(3, 128))
    # keypoints 1 and 3 carry landmark 0's descriptor; 3 comes later in the list, 1 sits exactly on the radius
    kp_uv = np.array([[300.0, 200.0], [60.0, 50.0], [200.0, 101.0], [52.0, 50.0], [1000.0, 1000.0]])
    kp_desc = _unit(np.stack([np.eye(128)[5], np.eye(128)[0], np.eye(128)[1], np.eye(128)[0], np.eye(128)[2]]))
    first, s1, s2 = row_best_two_within(lm_uv, lm_desc, kp_uv, kp_desc, 10.0)
    assert first[0] == 1 and s1[0] == pytest.approx(1.0) and s2[0] == pytest.approx(1.0)  # a tie: ratio test fails it
    assert first[1] == 2 and s1[1] == pytest.approx(1.0) and s2[1] == -np.inf  # one keypoint in reach
    assert first[2] == 0 and s1[2] == -np.inf and s2[2] == -np.inf  # none in reach


def test_no_points():
    lm = np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    kp = np.ones((3, 2)), _unit(np.ones((3, 128)))
    first, s1, s2 = row_best_two_within(*lm, *kp, 5.0)
    assert len(first) == len(s1) == len(s2) == 0
    first, s1, _ = row_best_two_within(*kp, *lm, 5.0)
    assert np.all(first == 0) and np.all(s1 == -np.inf)
    assert not tiles_pay(lm[0], kp[0], 5.0, 40.0)


def test_tiles_pay_for_wide_radii_only():
    lm_uv, _, kp_uv, _ = _points(0)
    assert tiles_pay(lm_uv, kp_uv, 60.0, 40.0)  # ~15 % of the entries are pairs in reach
    assert not tiles_pay(lm_uv, kp_uv, 3.0, 40.0)  # ~0.04 %: listing the pairs is cheaper
    assert tiles_pay(lm_uv, kp_uv, 3.0, 1e9) and not tiles_pay(lm_uv, kp_uv, 60.0, 0.0)
