"""The map diagnosis: reprojection of predicted coordinates, keypoint 3D error and the track-retrieval probe."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.accuracy.diagnosis import (
    BEHIND_PX,
    keypoint_errors,
    reprojection_px,
    track_retrieval,
    view_fit,
    view_fit_at,
)
from usvc.core.scene import Camera
from usvc.model.encoder import Encoder, cell_centers
from usvc.sfm.tracks_file import Tracks

K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])


def _backproject(h: int, w: int, depth: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    uv = cell_centers(h, w, "colmap").reshape(2, -1).T.numpy().astype(np.float64)
    rays = np.linalg.solve(K, np.vstack([uv.T, np.ones(len(uv))])).T
    cam = rays * depth
    return ((cam - t) @ R).reshape(h, w, 3)  # world = R^T (cam - t)


def test_reprojection_of_exact_coordinates_is_zero_and_errors_add_up():
    R, t = np.eye(3), np.array([0.1, -0.2, 0.5])
    coords = _backproject(6, 8, 2.0, R, t)
    assert np.abs(reprojection_px(coords, R, t, K)).max() < 1e-9
    shifted = coords.copy()
    shifted[..., 0] += 0.03  # x moved by 0.03 at camera depth 2: 100 * 0.03 / 2 = 1.5 px
    err = reprojection_px(shifted, R, t, K)
    assert np.median(err) == pytest.approx(100 * 0.03 / 2.0, rel=1e-6)
    behind = coords.copy()
    behind[0, 0] = [0.0, 0.0, -10.0]
    assert reprojection_px(behind, R, t, K)[0, 0] == BEHIND_PX


def test_keypoint_error_is_the_distance_to_the_triangulated_point():
    R, t = np.eye(3), np.zeros(3)
    coords = _backproject(6, 8, 2.0, R, t)
    uv = np.array([[4.5, 4.5], [12.5, 20.5], [8.5, 8.5]])  # two cell centres and a point between cells
    truth = np.linalg.solve(K, np.vstack([uv.T, np.ones(3)])).T * 2.0
    np.testing.assert_allclose(keypoint_errors(coords, uv, truth), 0.0, atol=1e-5)
    fit = view_fit(coords, R, t, K, uv, truth + [0.0, 0.0, 0.2], median_depth=2.0)
    assert fit.keypoint_err_rel == pytest.approx(0.1, rel=1e-4) and fit.keypoints == 3
    assert fit.median_px < 1e-6 and fit.inlier_10px == 1.0


def _tracks(uv_a: np.ndarray, uv_b: np.ndarray) -> Tracks:
    n = len(uv_a)
    return Tracks(image_names=["a", "b"], R=np.stack([np.eye(3)] * 2), t=np.zeros((2, 3)), K=np.stack([K] * 2),
                  point_id=np.arange(n), xyz=np.zeros((n, 3)), rgb=np.zeros((n, 3), np.uint8), error=np.zeros(n),
                  offset=np.arange(0, 2 * n + 1, 2), obs_image=np.tile([0, 1], n),
                  obs_uv=np.stack([uv_a, uv_b], 1).reshape(-1, 2), obs_descriptor=np.zeros((2 * n, 128), np.uint8),
                  obs_error=np.zeros(2 * n))


def test_track_retrieval_probe_scores_an_encoder_by_nearest_neighbours_across_images():
    torch.manual_seed(0)
    encoder = Encoder(width=0.25).eval()
    image = np.random.default_rng(0).random((96, 128)).astype(np.float32)
    uv = np.stack(np.meshgrid(np.arange(8, 120, 16) + 0.5, np.arange(8, 90, 16) + 0.5), -1).reshape(-1, 2)
    # the same photo twice, each track seen at the same pixel: every nearest neighbour is its own track
    same = track_retrieval(encoder, {"a": image, "b": image}, _tracks(uv, uv))
    assert same == {"observations": 2 * len(uv), "same_track_nn": 1.0}
    # the second image's observations shuffled among the tracks: no nearest neighbour is the track's own
    shuffled = track_retrieval(encoder, {"a": image, "b": image}, _tracks(uv, np.roll(uv, 1, axis=0)))
    assert shuffled["same_track_nn"] == 0.0


def test_a_map_at_a_smaller_working_resolution_is_scored_in_its_own_pixels():
    """A 128x96 photo mapped at half size: coordinates exact for the half-size camera reproject to 0 px
    there, and the photo's own keypoints (full-size pixels) land on the right cells."""
    camera = Camera("PINHOLE", 128, 96, (200.0, 200.0, 64.0, 48.0))
    R, t = np.eye(3), np.zeros(3)
    coords = _backproject(6, 8, 2.0, R, t)  # K above is this camera at 64x48
    np.testing.assert_allclose(camera.scaled(64, 48).K, K)
    uv_half = np.array([[4.5, 4.5], [28.5, 20.5]])  # cell centres of the 64x48 image
    xyz = np.linalg.solve(K, np.vstack([uv_half.T, np.ones(2)])).T * 2.0
    fit = view_fit_at(coords, (64, 48), camera, R, t, uv_half * 2, xyz, median_depth=2.0)
    assert fit.median_px < 1e-9 and fit.inlier_10px == 1.0
    assert fit.keypoints == 2 and fit.keypoint_err_rel < 1e-6
    # scored at the photo's own size instead, the same keypoints would miss their cells
    assert view_fit(coords, R, t, camera.K, uv_half * 2, xyz, 2.0).median_px > 10
