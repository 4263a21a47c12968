from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from usvc.core.errors import UsvcError
from usvc.core.pose_errors import rotation_error_deg, translation_error
from usvc.core.scene import CAMERA_MODELS, Camera
from usvc.relocalize.options import BACKENDS
from usvc.relocalize.pnp import solve_pnp

PINHOLE = Camera("PINHOLE", 640, 480, (525.0, 525.0, 320.0, 240.0))
R_TRUE = Rotation.from_euler("xyz", [12.0, -30.0, 75.0], degrees=True).as_matrix()
T_TRUE = np.array([0.4, -0.3, 1.2])


def make_correspondences(camera: Camera, n: int = 400, outlier_ratio: float = 0.5, seed: int = 0):
    """Noiseless points projected with COLMAP's own camera model (the pixel convention under test)."""
    rng = np.random.default_rng(seed)
    cam = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                          params=list(camera.params))
    x_cam = np.c_[rng.uniform(-0.55, 0.55, (n, 1)), rng.uniform(-0.42, 0.42, (n, 1)), np.ones(n)]
    x_cam *= rng.uniform(1.0, 4.0, (n, 1))
    uv = np.asarray(cam.img_from_cam(x_cam), dtype=np.float64)
    x_world = (x_cam - T_TRUE) @ R_TRUE
    outlier = rng.permutation(n) < round(outlier_ratio * n)
    x_world[outlier] = rng.uniform(-3.0, 3.0, (int(outlier.sum()), 3))
    return uv, x_world, outlier


OPENCV = Camera("OPENCV", 640, 480, (500.0, 510.0, 321.0, 239.0, -0.2, 0.05, 1e-3, -2e-3))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("camera", [PINHOLE, OPENCV], ids=["PINHOLE", "OPENCV"])
def test_recovers_known_pose_with_half_outliers(backend, camera):
    uv, xw, outlier = make_correspondences(camera)
    res = solve_pnp(uv, xw, camera, backend=backend)
    assert res.success
    assert rotation_error_deg(res.R, R_TRUE) < 1e-3
    assert translation_error(res.R, res.t, R_TRUE, T_TRUE) < 1e-4
    np.testing.assert_array_equal(res.inlier_mask, ~outlier)
    assert res.num_inliers == int((~outlier).sum())
    assert res.seconds > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_same_seed_same_pose(backend):
    uv, xw, _ = make_correspondences(PINHOLE, outlier_ratio=0.6, seed=3)
    uv = uv + np.random.default_rng(1).normal(0.0, 1.0, uv.shape)  # noise, so runs could differ
    a = solve_pnp(uv, xw, PINHOLE, seed=7, backend=backend)
    b = solve_pnp(uv, xw, PINHOLE, seed=7, backend=backend)
    assert a.success and b.success
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)


@pytest.mark.parametrize("backend", BACKENDS)
def test_too_few_inliers_is_failure_not_error(backend):
    uv, xw, outlier = make_correspondences(PINHOLE, n=200, outlier_ratio=0.9)
    res = solve_pnp(uv, xw, PINHOLE, min_inliers=50, backend=backend)
    assert not res.success
    assert np.isnan(res.R).all() and np.isnan(res.t).all()
    assert res.inlier_mask.shape == (200,)


def test_backends_agree_on_colmap_pixel_convention():
    # Points come from pycolmap's projection (top-left pixel centre at (0.5, 0.5)); a backend that
    # shifted only the points or only the principal point would be off by ~0.05 deg here.
    uv, xw, _ = make_correspondences(PINHOLE, outlier_ratio=0.3, seed=5)
    a = solve_pnp(uv, xw, PINHOLE, backend="pycolmap")
    b = solve_pnp(uv, xw, PINHOLE, backend="opencv")
    assert rotation_error_deg(a.R, b.R) < 1e-6
    assert translation_error(a.R, a.t, b.R, b.t) < 1e-7
    shifted = solve_pnp(uv - 0.5, xw, PINHOLE, backend="opencv")
    assert rotation_error_deg(shifted.R, R_TRUE) > 1e-2


def test_nonfinite_points_are_dropped():
    uv, xw, outlier = make_correspondences(PINHOLE, n=200)
    uv[0] = np.nan
    xw[1, 2] = np.inf
    for backend in BACKENDS:
        res = solve_pnp(uv, xw, PINHOLE, backend=backend)
        assert res.success and not res.inlier_mask[0] and not res.inlier_mask[1]
        assert rotation_error_deg(res.R, R_TRUE) < 1e-3


def test_malformed_inputs_raise():
    uv, xw, _ = make_correspondences(PINHOLE, n=20, outlier_ratio=0.0)
    with pytest.raises(UsvcError, match="correspondences"):
        solve_pnp(uv[:10], xw, PINHOLE)
    with pytest.raises(UsvcError, match="correspondences"):
        solve_pnp(uv, xw[:, :2], PINHOLE)
    with pytest.raises(UsvcError, match="at least 4"):
        solve_pnp(uv[:3], xw[:3], PINHOLE)
    bad = xw[:5].copy()
    bad[:2] = np.nan
    with pytest.raises(UsvcError, match="at least 4"):
        solve_pnp(uv[:5], bad, PINHOLE)
    with pytest.raises(UsvcError, match="backend"):
        solve_pnp(uv, xw, PINHOLE, backend="magic")


def test_a_low_trial_floor_leaves_the_adaptive_stop_in_charge():
    # min_trials only lowers the floor of RANSAC's search: where inliers are few (80 % outliers
    # here, with pixel noise) the adaptive count still runs the trials the confidence needs.
    uv, xw, outlier = make_correspondences(PINHOLE, n=500, outlier_ratio=0.8, seed=11)
    uv = uv + np.random.default_rng(2).normal(0.0, 0.5, uv.shape)
    res = solve_pnp(uv, xw, PINHOLE, max_error_px=4.0, backend="pycolmap", min_trials=1)
    assert res.success
    assert rotation_error_deg(res.R, R_TRUE) < 0.1
    assert res.inlier_mask[outlier].sum() <= 2 and res.inlier_mask[~outlier].mean() > 0.95
    # on clean correspondences the floor only shortens the search: the same refined pose
    clean_uv, clean_xw, _ = make_correspondences(PINHOLE, n=500, outlier_ratio=0.01, seed=12)
    clean_uv = clean_uv + np.random.default_rng(3).normal(0.0, 0.5, clean_uv.shape)
    low = solve_pnp(clean_uv, clean_xw, PINHOLE, max_error_px=4.0, backend="pycolmap", min_trials=5)
    full = solve_pnp(clean_uv, clean_xw, PINHOLE, max_error_px=4.0, backend="pycolmap")
    np.testing.assert_array_equal(low.inlier_mask, full.inlier_mask)
    assert rotation_error_deg(low.R, full.R) < 1e-6 and translation_error(low.R, low.t, full.R, full.t) < 1e-7


def test_min_trials_is_the_lo_ransac_backends_and_bounded():
    uv, xw, _ = make_correspondences(PINHOLE, n=50, outlier_ratio=0.0)
    with pytest.raises(UsvcError, match="min_trials=10: only the pycolmap and poselib backends"):
        solve_pnp(uv, xw, PINHOLE, backend="opencv", min_trials=10)
    for backend in ("pycolmap", "poselib"):
        with pytest.raises(UsvcError, match="min_trials=0"):
            solve_pnp(uv, xw, PINHOLE, backend=backend, min_trials=0)
        assert solve_pnp(uv, xw, PINHOLE, backend=backend, min_trials=10).success


@pytest.mark.parametrize("camera", [PINHOLE, OPENCV], ids=["PINHOLE", "OPENCV"])
def test_poselib_and_colmap_give_one_pose_on_noisy_nearly_all_inlier_matches(camera):
    # what the feature passes give them: ~1 % outliers, half-pixel noise. Both minimise the same
    # Cauchy loss of 1 px over the same inliers, so they agree far below the noise's own effect
    # (the pose moves by ~0.01 deg and ~1e-4 of the distance from one noise draw to the next)
    uv, xw, outlier = make_correspondences(camera, n=600, outlier_ratio=0.01, seed=21)
    noisy = uv + np.random.default_rng(4).normal(0.0, 0.5, uv.shape)
    a = solve_pnp(noisy, xw, camera, max_error_px=4.0, backend="pycolmap", min_trials=20)
    b = solve_pnp(noisy, xw, camera, max_error_px=4.0, backend="poselib", min_trials=20)
    assert a.success and b.success
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    assert not b.inlier_mask[outlier].any()
    assert rotation_error_deg(a.R, b.R) < 1e-3 and translation_error(a.R, a.t, b.R, b.t) < 1e-5
    other = solve_pnp(uv + np.random.default_rng(5).normal(0.0, 0.5, uv.shape), xw, camera, max_error_px=4.0,
                      backend="pycolmap", min_trials=20)
    assert rotation_error_deg(a.R, other.R) > 10 * rotation_error_deg(a.R, b.R)  # the margin means something


@pytest.mark.parametrize("model", sorted(CAMERA_MODELS))
def test_poselib_projects_every_camera_model_as_colmap_does(model):
    import poselib

    extra = {"SIMPLE_PINHOLE": (), "PINHOLE": (), "SIMPLE_RADIAL": (-0.05,), "RADIAL": (-0.05, 0.01),
             "OPENCV": (-0.1, 0.02, 1e-3, -2e-3), "OPENCV_FISHEYE": (0.05, -0.01, 2e-3, -1e-3),
             "FULL_OPENCV": (-0.1, 0.02, 1e-3, -2e-3, 1e-3, 0.01, -2e-3, 1e-4)}[model]
    base = (500.0,) if model.startswith("SIMPLE") or model == "RADIAL" else (500.0, 510.0)
    params = [*base, 321.0, 239.0, *extra]
    assert len(params) == CAMERA_MODELS[model]
    normalized = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 2))
    colmap = pycolmap.Camera(model=model, width=640, height=480, params=params)
    expected = np.asarray(colmap.img_from_cam(np.c_[normalized, np.ones(50)]), np.float64)
    got = poselib.Camera(model, params, 640, 480).project(normalized)
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_feature_pnps_use_the_lower_trial_floor(monkeypatch):
    from usvc.relocalize.features import passes as F

    seen = {}

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return solve_pnp(*args, **kwargs)

    monkeypatch.setattr(F, "solve_pnp", spy)
    uv, xw, _ = make_correspondences(PINHOLE, n=100, outlier_ratio=0.1)
    opts = F.FeatureMatchOptions(radii_px=(8.0,), ratio=0.8, max_error_px=4.0, min_inliers=20, view_margin_deg=45.0)
    res = F._pnp(uv, xw, PINHOLE, opts, seed=0)
    assert res is not None and rotation_error_deg(res.R, R_TRUE) < 1e-3
    assert seen["backend"] == "poselib" and seen["min_trials"] == F.FEATURE_MIN_TRIALS < 100
    res = F._pnp(uv, xw, PINHOLE, F.replace(opts, pnp="pycolmap"), seed=0)
    assert res is not None and seen["backend"] == "pycolmap"


def test_sift_and_pnps_own_evidence_keeps_colmaps_pnp(monkeypatch):
    # the verified path is SIFT + PnP's registration of a query: COLMAP's LO-RANSAC, as the baseline
    from usvc.relocalize.features import passes as F

    seen = []

    def spy(*args, **kwargs):
        seen.append(kwargs["backend"])
        return solve_pnp(*args, **kwargs)

    monkeypatch.setattr(F, "solve_pnp", spy)
    uv, xw, _ = make_correspondences(PINHOLE, n=100, outlier_ratio=0.1)

    class Found:  # the parts of VerifiedMatches that from_verified reads
        images, verified_pairs, keypoint, landmark = 3, 3, np.arange(100), np.arange(100)

        def __len__(self):
            return 100

    class Map:  # the parts of Landmarks it reads
        xyz, image_short_side = xw, 480

    opts = F.FeatureMatchOptions(radii_px=(8.0,), ratio=0.8, max_error_px=4.0, min_inliers=20, view_margin_deg=45.0)
    feats = type("Feats", (), {"uv": uv})()
    out = F.from_verified(Map(), np.zeros((100, 128), np.float32), feats, PINHOLE, Found(), opts)
    assert out.success and out.path == "verified" and seen == ["pycolmap"]


@pytest.mark.parametrize("camera", [PINHOLE, Camera("SIMPLE_PINHOLE", 320, 240, (260.0, 161.0, 119.0)), OPENCV,
                                    Camera("SIMPLE_RADIAL", 640, 480, (500.0, 321.0, 239.0, -0.05))],
                         ids=["PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL"])
def test_project_points_is_colmaps_projection(camera):
    # the pinhole models take numpy's arithmetic, the others OpenCV's projectPoints: both COLMAP's pixels
    from usvc.relocalize.pnp import project_points

    rng = np.random.default_rng(8)
    xw = rng.uniform(-2.0, 2.0, (500, 3))
    uv, depth = project_points(camera, xw, R_TRUE, T_TRUE)
    x_cam = xw @ R_TRUE.T + T_TRUE
    np.testing.assert_allclose(depth, x_cam[:, 2], rtol=0, atol=1e-12)
    front = x_cam[:, 2] > 0.1
    colmap = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=list(camera.params))
    expected = np.asarray(colmap.img_from_cam(x_cam[front]), np.float64)
    tolerance = 1e-9 if camera.model.endswith("PINHOLE") else 1e-5  # OpenCV's distortion polynomial rounds differently far out
    np.testing.assert_allclose(uv[front], expected, rtol=0, atol=tolerance)
    assert project_points(camera, np.zeros((0, 3)), R_TRUE, T_TRUE)[0].shape == (0, 2)
