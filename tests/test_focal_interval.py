"""The focal lengths a photo's matches allow (`focal_log_std`) and the features' focal verdict built
on them: a deep view pins the focal length, a flat one leaves it free, and the verdict refuses,
vouches or defers accordingly."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from usvc.core.absolute_pose import estimate_focal_pose, focal_log_std
from usvc.core.scene import Camera
from usvc.relocalize.features.path import FOCAL_UNOBSERVABLE, feature_focal_verdict

W, H, F = 640, 480, 500.0


def view(depth_spread: float, noise_px: float, seed: int, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and the points they see from the identity pose: points on rays through random
    pixels, at depths 5 m x (1 +- depth_spread), the pixels then perturbed by `noise_px`."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([20, 20], [W - 20, H - 20], (n, 2))
    depth = 5.0 * rng.uniform(1.0 - depth_spread, 1.0 + depth_spread, n) if depth_spread else np.full(n, 5.0)
    xyz = np.stack([(uv[:, 0] - W / 2) / F, (uv[:, 1] - H / 2) / F, np.ones(n)], 1) * depth[:, None]
    return uv + rng.normal(0.0, noise_px, uv.shape), xyz


def test_the_standard_deviation_is_that_of_repeated_estimates():
    """Over noise draws, P4Pf's ln(focal) scatters as much as the covariance says (within the
    sampling error of 40 draws), and about the truth."""
    logs, stds = [], []
    for seed in range(40):
        uv, xyz = view(0.3, 1.0, seed)
        found = estimate_focal_pose(uv, xyz, W, H, 6.0)
        assert found is not None
        logs.append(np.log(found.camera.params[0] / F))
        stds.append(focal_log_std(found, uv, xyz))
    spread, predicted = float(np.std(logs)), float(np.median(stds))
    assert 0.6 < spread / predicted < 1.6, (spread, predicted)
    assert abs(np.mean(logs)) < 4 * predicted / np.sqrt(40)


def test_a_flat_view_leaves_the_focal_length_free_and_a_deep_one_pins_it():
    deep = [focal_log_std(estimate_focal_pose(*view(0.5, 0.5, s), W, H, 4.0), *view(0.5, 0.5, s)) for s in range(3)]
    shallow = [focal_log_std(estimate_focal_pose(*view(0.02, 0.5, s), W, H, 4.0), *view(0.02, 0.5, s))
               for s in range(3)]
    assert max(deep) < 0.01 and min(shallow) > 10 * max(deep), (deep, shallow)
    uv, xyz = view(0.0, 0.5, 0)  # a plane facing the camera: distance and focal length trade exactly
    found = estimate_focal_pose(uv, xyz, W, H, 4.0)
    assert found is None or focal_log_std(found, uv, xyz) > 0.1


TOLERANCE = 0.25  # relocalize.focal_tolerance


def _evidence(uv: np.ndarray, xyz: np.ndarray, focal: float) -> SimpleNamespace:
    camera = Camera("PINHOLE", W, H, (focal, focal, W / 2, H / 2))
    return SimpleNamespace(camera=camera, opts=SimpleNamespace(max_error_px=4.0, min_inliers=20),
                           focal_poses=lambda global_matches=True, verified=False: iter(
                               [(uv, xyz, estimate_focal_pose(uv, xyz, W, H, 4.0, 0))]))


@pytest.mark.parametrize("depth_spread", [0.3, 0.08])
def test_the_features_vouch_for_a_right_focal_length_and_refuse_a_wrong_one(depth_spread: float):
    """A view deep enough to pin the focal length (0.08: a near-flat one, which a test of how many
    inliers a 25 % wrong focal length keeps at the PnP threshold could not tell from a flat one)."""
    uv, xyz = view(depth_spread, 0.5, 1)
    assert feature_focal_verdict(_evidence(uv, xyz, F), TOLERANCE) == ""
    assert feature_focal_verdict(_evidence(uv, xyz, 1.1 * F), TOLERANCE) == ""  # within the tolerance
    for factor in (2.0, 0.5, 1.4):
        why = feature_focal_verdict(_evidence(uv, xyz, factor * F), TOLERANCE)
        found = re.match(r"the matched features imply a focal length (\d+\.\d+)x the given one", why)
        assert found and abs(np.log(float(found.group(1)) * factor)) < 0.03, why


def test_the_features_defer_where_the_view_allows_the_focal_length_and_one_far_off():
    """A near-flat view with coarse matches allows focal lengths well beyond the tolerance either
    way: the features neither refuse the given one nor vouch for it; the map, or nothing, decides."""
    uv, xyz = view(0.005, 3.0, 2)
    for factor in (1.0, 2.0, 0.5):
        assert feature_focal_verdict(_evidence(uv, xyz, factor * F), TOLERANCE) == FOCAL_UNOBSERVABLE
