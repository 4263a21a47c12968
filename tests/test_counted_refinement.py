"""The images pass's refinement on repeated correspondences (usvc/relocalize/counted_refinement.py)
and its per-image matching (`pose_checked_matches`): a pair counted n times is one pair weighted
n, the same pose as COLMAP's refinement given every repetition; only the keypoints the pose puts
within reach of an image's landmarks are compared with that image's observations."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_fallback import N_POINTS, scene
from test_refinement import CAM, R_TRUE, T_TRUE, errors

from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import unit_descriptors
from usvc.relocalize.counted_refinement import _cost, _residuals, distinct_pairs, refine_weighted
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import pose_checked_matches, verified_matches
from usvc.relocalize.pnp import project_points, refine_on_inliers

R_START = Rotation.from_rotvec([0.0, 0.004, 0.002]).as_matrix() @ R_TRUE  # ~0.26 deg off
T_START = T_TRUE + np.array([0.003, -0.002, 0.004])


def _correspondences(seed: int = 0, n: int = 300, outliers: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uv, xyz, counts): points seen by the true pose with 0.3 px noise, some outliers, each
    correspondence repeated 1-9 times."""
    rng = np.random.default_rng(seed)
    xyz = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2.5, 4.0, n)]
    xyz = (xyz - T_TRUE) @ R_TRUE  # world points that the true camera sees in front of it
    uv, _ = project_points(CAM, xyz, R_TRUE, T_TRUE)
    uv = uv + rng.normal(0, 0.3, uv.shape)
    uv[:outliers] += rng.uniform(-3.0, 3.0, (outliers, 2))  # within the 4 px threshold: the loss, not the mask
    return uv, xyz, rng.integers(1, 10, n)


def _pose_gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    (Ra, ta), (Rb, tb) = a, b
    angle = np.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude())
    return float(angle), float(np.linalg.norm(Ra.T @ ta - Rb.T @ tb))


def _colmap(uv: np.ndarray, xyz: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's refinement, converged tightly (its default stop is a gradient tolerance of 1)."""
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.gradient_tolerance = 1e-12
    cam = pycolmap.Camera(model=CAM.model, width=CAM.width, height=CAM.height, params=list(CAM.params))
    res = pycolmap.refine_absolute_pose(pycolmap.Rigid3d(pycolmap.Rotation3d(R), t), uv.astype(np.float64),
                                        xyz.astype(np.float64), np.ones(len(uv), bool), cam, options)
    pose = res["cam_from_world"]
    return pose.rotation.matrix(), np.asarray(pose.translation, np.float64)


def test_weighted_refinement_is_colmaps_on_the_repetitions():
    uv, xyz, counts = _correspondences()
    rows = np.repeat(np.arange(len(uv)), counts)
    R, t, ok = refine_weighted(uv, xyz, counts, CAM, R_START, T_START)
    colmap = _colmap(uv[rows], xyz[rows], R_START, T_START)
    angle, shift = _pose_gap((R, t), colmap)
    assert ok and angle < 1e-3 and shift < 1e-4  # the same minimum: the start was 0.3 deg and 9e-3 from it
    assert _pose_gap((R_START, T_START), colmap)[1] > 5e-3
    f, c = np.asarray(CAM.focal), np.asarray(CAM.principal_point)
    cost = [_cost((_residuals(uv, xyz, *pose, f, c)[0] ** 2).sum(1), counts, 1.0) for pose in [(R, t), colmap]]
    assert cost[0] <= cost[1] + 1e-9  # as low as COLMAP's (which stops at its function tolerance)
    # unit weights: COLMAP's on the pairs once each; the counts are what moved the pose
    once = refine_weighted(uv, xyz, np.ones(len(uv)), CAM, R_START, T_START)
    assert _pose_gap(once[:2], _colmap(uv, xyz, R_START, T_START))[1] < 1e-4
    assert _pose_gap(once[:2], (R, t))[1] > 10 * shift


def test_refinement_with_counts_equals_the_repeated_one_and_fails_like_it():
    uv, xyz, counts = _correspondences(1)
    rows = np.repeat(np.arange(len(uv)), counts)
    counted = refine_on_inliers(uv, xyz, CAM, R_START, T_START, 4.0, counts=counts)
    repeated = refine_on_inliers(uv[rows], xyz[rows], CAM, R_START, T_START, 4.0)
    assert counted.success and repeated.success
    angle, shift = _pose_gap((counted.R, counted.t), (repeated.R, repeated.t))
    assert angle < 1e-3 and shift < 1e-4  # COLMAP stops at its own tolerance; both near the truth
    assert errors(counted.R, counted.t)[0] < errors(R_START, T_START)[0] / 2
    assert counted.inlier_mask.shape == (len(uv),) and np.array_equal(counted.inlier_mask[rows], repeated.inlier_mask)
    far = refine_on_inliers(uv, xyz, CAM, R_TRUE, T_TRUE + np.array([1.0, 0.0, 0.0]), 4.0, counts=counts)
    assert not far.success and np.isnan(far.R).all() and np.isnan(far.t).all()


def test_a_distorted_camera_gets_colmaps_refinement_on_the_repetitions():
    uv, xyz, counts = _correspondences(2)
    (fx, _), (cx, cy) = CAM.focal, CAM.principal_point
    radial = Camera("SIMPLE_RADIAL", CAM.width, CAM.height, (fx, cx, cy, 0.0))  # no distortion: the pinhole path
    assert not radial.has_distortion
    bent = Camera("SIMPLE_RADIAL", CAM.width, CAM.height, (fx, cx, cy, 1e-3))
    with pytest.raises(ValueError, match="undistorted"):
        refine_weighted(uv, xyz, counts, bent, R_START, T_START)
    rows = np.repeat(np.arange(len(uv)), counts)
    res = refine_on_inliers(uv, xyz, bent, R_START, T_START, 4.0, counts=counts)
    colmap = refine_on_inliers(uv[rows], xyz[rows], bent, R_START, T_START, 4.0)
    assert res.success and np.array_equal(res.R, colmap.R) and np.array_equal(res.t, colmap.t)
    assert res.inlier_mask.shape == (len(uv),) and res.num_inliers == int(res.inlier_mask.sum())
    plain = refine_on_inliers(uv, xyz, radial, R_START, T_START, 4.0, counts=counts)  # = the same pinhole's
    pinhole = refine_on_inliers(uv, xyz, Camera("PINHOLE", CAM.width, CAM.height, (fx, fx, cx, cy)), R_START,
                                T_START, 4.0, counts=counts)
    assert plain.success and np.array_equal(plain.R, pinhole.R) and np.array_equal(plain.t, pinhole.t)


def test_distinct_pairs_keep_the_first_of_each_in_order_with_its_count():
    keypoint = np.array([5, 2, 5, 5, 2, 7, 2])
    landmark = np.array([1, 3, 1, 4, 3, 0, 3])
    rows, counts = distinct_pairs(keypoint, landmark)
    assert rows.tolist() == [0, 1, 3, 5] and counts.tolist() == [2, 3, 1, 1]
    empty_rows, empty_counts = distinct_pairs(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert len(empty_rows) == 0 and len(empty_counts) == 0


def test_a_keypoint_out_of_the_poses_reach_does_not_take_a_landmark_from_the_one_in_it():
    """Each image is compared only with the keypoints the pose puts within the threshold of one of
    its landmarks: a far keypoint whose descriptor is a copy of an observation's own can no longer
    win that observation's mutual test from the right keypoint, and adds nothing."""
    landmarks, feats = scene()
    every = np.arange(len(landmarks))
    base = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every, 2.0)
    obs = landmarks.observations
    image, a, b = obs.image_slices()[0]
    j = a + int(np.flatnonzero(obs.landmark[a:b] == base.landmark[0])[0])  # its observation in the first image
    uv, _ = project_points(CAM, landmarks.xyz, R_TRUE, T_TRUE)
    spot = np.array([CAM.width, CAM.height], float) * 0.5
    while np.min(np.linalg.norm(uv - spot, axis=1)) < 10.0:  # a place no landmark projects near
        spot = spot + np.array([1.7, 0.9])
    code = obs.descriptor[j][None]  # the observation's own bytes
    copied = QueryFeatures(np.concatenate([feats.uv, spot[None]]),
                           np.concatenate([feats.descriptor, unit_descriptors(code)]),
                           np.concatenate([feats.codes, code]))
    found = pose_checked_matches(landmarks, copied, CAM, R_TRUE, T_TRUE, every, 2.0)
    assert np.array_equal(found.keypoint, base.keypoint) and np.array_equal(found.landmark, base.landmark)
    assert image == obs.image_slices()[0][0]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[
    pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")])])
def test_per_image_matching_on_a_device_is_numpys(device):
    """A relocalizer on a GPU computes the per-image products there (`device_matching.mutual_reductions`);
    torch's path (on the CPU, or the card) gives numpy's matches, verified or pose-checked."""
    landmarks, feats = scene()
    every = np.arange(len(landmarks))
    for run in (lambda d: verified_matches(landmarks, feats, CAM, seed=3, threads=2, device=d),
                lambda d: pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every, 2.0, threads=2, device=d)):
        on_numpy, on_torch = run(None), run(device)
        assert len(on_numpy) > N_POINTS
        for name in ("uv", "xyz", "landmark", "keypoint"):
            assert np.array_equal(getattr(on_torch, name), getattr(on_numpy, name)), name
