"""Keypoint-guided pose refinement (paper §3.2.2), its map keypoints and its per-query records.

The synthetic query: a known camera over a smooth depth map, one cell per 8x8 block. Cells near
the map's keypoints get exact scene coordinates; the others get coordinates consistent with a
slightly wrong pose (plus noise), so dense RANSAC-PnP lands between the two and refinement on
the keypoint cells alone can recover the true pose.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from usvc.core.pose_errors import rotation_error_deg
from usvc.core.scene import Camera, Frame
from usvc.model.encoder import Encoder, cell_centers
from usvc.model.errors import ModelError
from usvc.model.head import Head, Regressor
from usvc.model.map_file import map_keypoints, read_map_header, save_map
from usvc.relocalize.keypoint_refinement import (
    RefineResult,
    keypoint_cell_mask,
    pose_change,
    refine_pose,
)
from usvc.relocalize.pnp import project_points, reprojection_inliers, solve_pnp
from usvc.relocalize.pose_estimate import PoseEstimate
from usvc.relocalize.relocalizer import (
    RelocalizeOptions,
    Relocalizer,
    refine_options,
)
from usvc.relocalize.run import write_results

CAM = Camera("PINHOLE", 160, 120, (130.0, 125.0, 81.0, 59.0))  # 20x15 cells
H_CELLS, W_CELLS = 15, 20
THRESHOLD = 10.0 * 120 / 480  # the Relocalizer's default threshold at this working size
R_TRUE = Rotation.from_rotvec([0.1, -0.3, 0.05]).as_matrix()
T_TRUE = np.array([0.2, -0.1, 1.5])
MEDIAN_DEPTH = 2.0
# Keypoints project 2 px right and below these cells' centres: 3 cells lie within 8 px of each
# (its own, the one to the right, the one below) with > 1.5 px to spare, so masks are stable.
KEYPOINT_CELLS = [(2, 3), (2, 10), (2, 16), (7, 6), (7, 13), (12, 3), (12, 10), (12, 16), (5, 1), (9, 18)]

PIXELS = cell_centers(H_CELLS, W_CELLS, "colmap").permute(1, 2, 0).reshape(-1, 2).double().numpy()


def backproject(uv: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points seen at pixels `uv` by (R, t) on a smooth, non-planar depth map."""
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    x, y = (uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy
    depth = MEDIAN_DEPTH + 0.4 * x + 0.3 * np.cos(3.0 * y)
    return (np.stack([x * depth, y * depth, depth], -1) - t) @ R


def perturbed(rotvec: list[float], dt: list[float]) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_rotvec(rotvec).as_matrix() @ R_TRUE, T_TRUE + np.array(dt)


KEYPOINTS = backproject(PIXELS[[i * W_CELLS + j for i, j in KEYPOINT_CELLS]] + 2.0, R_TRUE, T_TRUE)
NEAR = np.min(np.linalg.norm(PIXELS[:, None] - (PIXELS[[i * W_CELLS + j for i, j in KEYPOINT_CELLS]] + 2.0)[None],
                             axis=2), axis=1) <= 12.0  # cells that stay masked for any pose near the truth
SMALL_BIAS = perturbed([0.0, 0.006, 0.0], [0.004, -0.006, 0.01])  # ~0.7 px mean, 1.5 px max off at the truth
LARGE_BIAS = perturbed([0.0, 0.0, 0.0], [0.08, 0.0, 0.0])  # 4.1-5.7 px off: outside the 2.5 px threshold


def coordinate_map(near: tuple[np.ndarray, np.ndarray], far: tuple[np.ndarray, np.ndarray],
                   noise: float = 0.002, seed: int = 0) -> np.ndarray:
    """(N,3): cells near keypoints consistent with pose `near`, the rest with pose `far` plus noise."""
    rng = np.random.default_rng(seed)
    far_xyz = backproject(PIXELS, *far) + rng.normal(0.0, noise, (len(PIXELS), 3))
    return np.where(NEAR[:, None], backproject(PIXELS, *near), far_xyz)


def dense_pose(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    res = solve_pnp(PIXELS, coords, CAM, max_error_px=THRESHOLD)
    assert res.success
    return res.R, res.t, res.num_inliers


def errors(R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    return float(rotation_error_deg(R, R_TRUE)), float(np.linalg.norm(t - T_TRUE))


def refine(coords: np.ndarray, R0: np.ndarray, t0: np.ndarray, keypoints: np.ndarray = KEYPOINTS,
           **opts: float) -> RefineResult:
    return refine_pose(PIXELS, coords, CAM, keypoints, R0, t0, max_error_px=THRESHOLD,
                       median_depth=MEDIAN_DEPTH,
                       options=dataclasses.replace(refine_options(RelocalizeOptions()), **opts))


# --- the synthetic setup is what the tests assume ------------------------------------------

def test_setup_puts_the_dense_pose_off_and_keypoint_cells_in_the_mask():
    assert 60 <= NEAR.sum() <= 120  # a minority of the 300 cells is accurate
    R0, t0, inliers = dense_pose(coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS))
    rot, trans = errors(R0, t0)
    assert rot > 0.1 and trans > 0.004  # the biased majority pulls the dense pose off
    assert inliers == 300  # ... but every cell still agrees with it within 2.5 px
    mask = keypoint_cell_mask(PIXELS, CAM, KEYPOINTS, R_TRUE, T_TRUE, 8.0)
    assert mask.sum() == 3 * len(KEYPOINT_CELLS) and np.all(NEAR[mask])
    assert np.array_equal(mask, keypoint_cell_mask(PIXELS, CAM, KEYPOINTS, R0, t0, 8.0))


def test_mask_ignores_keypoints_behind_the_camera_or_outside_the_image():
    behind = 2 * (-R_TRUE.T @ T_TRUE) - KEYPOINTS  # mirrored through the camera centre
    assert not keypoint_cell_mask(PIXELS, CAM, behind, R_TRUE, T_TRUE, 8.0).any()
    uv, depth = project_points(CAM, KEYPOINTS, R_TRUE, T_TRUE)
    assert np.all(depth > 0) and np.allclose(uv, PIXELS[[i * W_CELLS + j for i, j in KEYPOINT_CELLS]] + 2.0)
    off = backproject(np.array([[165.0, 60.0], [-3.0, 60.0], [80.0, 123.0]]), R_TRUE, T_TRUE)  # just outside
    assert not keypoint_cell_mask(PIXELS, CAM, off, R_TRUE, T_TRUE, 8.0).any()
    assert keypoint_cell_mask(PIXELS, CAM, off, R_TRUE, T_TRUE, 50.0).sum() == 0  # outside stays out at any radius


# --- refinement ---------------------------------------------------------------------------

def test_refinement_moves_the_pose_to_the_truth():
    coords = coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS)
    R0, t0, inliers0 = dense_pose(coords)
    res = refine(coords, R0, t0)
    rot0, trans0 = errors(R0, t0)
    rot, trans = errors(res.R, res.t)
    assert res.kept and 1 <= res.iterations < 5  # converges before T_max
    assert rot < 0.01 * rot0 and trans < 0.01 * trans0
    assert rot < 1e-3 and trans < 1e-5
    assert res.masked == 3 * len(KEYPOINT_CELLS)
    assert res.initial_inliers == inliers0 == 300 and res.final_inliers == 300 and res.inliers == 300
    assert np.array_equal(res.initial_R, R0) and np.array_equal(res.initial_t, t0)


def test_refinement_respects_max_iterations(monkeypatch):
    import usvc.relocalize.keypoint_refinement as refinement

    coords = coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS)
    R0, t0, _ = dense_pose(coords)
    # a pose that never settles (delta must be > 0): T_max alone decides how many PnP solves run
    monkeypatch.setattr(refinement, "pose_change", lambda *args: float("inf"))
    assert refine(coords, R0, t0, max_iterations=3).iterations == 3
    one = refine(coords, R0, t0, max_iterations=1)
    assert one.iterations == 1 and one.kept
    assert errors(one.R, one.t)[0] < 1e-3


def test_convergence_test_is_scale_free():
    R1, t1 = perturbed([0.0, 0.0, 0.0], [0.0, 0.0, 0.5])
    assert pose_change(R_TRUE, T_TRUE, R1, t1, median_depth=1.0) == pytest.approx(0.5)
    assert pose_change(R_TRUE, T_TRUE, R1, t1, median_depth=100.0) == pytest.approx(0.005)
    R2 = Rotation.from_rotvec([0.0, 0.0, 0.1]).as_matrix() @ R_TRUE
    assert pose_change(R_TRUE, T_TRUE, R2, T_TRUE, 1.0) == pytest.approx(2 * np.sqrt(2) * np.sin(0.05))


def test_too_few_masked_cells_keeps_the_initial_pose():
    coords = coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS)
    R0, t0, _ = dense_pose(coords)
    res = refine(coords, R0, t0, keypoints=KEYPOINTS[:6])  # 6 keypoints mask 18 cells < 20
    assert res.masked == 18
    assert res.iterations == 0 and not res.kept
    assert np.array_equal(res.R, R0) and np.array_equal(res.t, t0)
    assert res.final_inliers == res.initial_inliers == 300
    # one more keypoint (21 cells) is enough, and so is a lower minimum
    seven = refine(coords, R0, t0, keypoints=KEYPOINTS[:7])
    assert seven.masked == 21 and seven.iterations >= 1 and seven.kept and errors(seven.R, seven.t)[0] < 1e-3
    assert refine(coords, R0, t0, keypoints=KEYPOINTS[:6], min_correspondences=18).iterations >= 1


def test_refined_pose_that_explains_fewer_cells_is_rejected():
    # keypoint cells agree on a wrong pose, every other cell on the truth: the refined pose
    # fits the keypoint cells but loses most of the dense inliers, so the dense pose stays
    coords = coordinate_map(LARGE_BIAS, (R_TRUE, T_TRUE), noise=0.0)
    R0, t0, inliers0 = dense_pose(coords)
    assert errors(R0, t0)[0] < 1e-3 and inliers0 == 300 - NEAR.sum()
    res = refine(coords, R0, t0)
    assert res.iterations >= 1 and not res.kept
    assert res.final_inliers == NEAR.sum() < res.initial_inliers == inliers0  # it fits only the keypoint cells
    assert np.array_equal(res.R, R0) and np.array_equal(res.t, t0) and res.inliers == inliers0


def test_reprojection_inliers_counts_front_points_within_threshold():
    coords = backproject(PIXELS, R_TRUE, T_TRUE)
    assert reprojection_inliers(CAM, PIXELS, coords, R_TRUE, T_TRUE, 0.5).all()
    shifted = PIXELS + np.array([3.0, 0.0])
    assert reprojection_inliers(CAM, shifted, coords, R_TRUE, T_TRUE, 3.1).all()
    assert not reprojection_inliers(CAM, shifted, coords, R_TRUE, T_TRUE, 2.9).any()
    coords[:5] = np.nan
    mask = reprojection_inliers(CAM, PIXELS, coords, R_TRUE, T_TRUE, 0.5)
    assert mask.sum() == 295 and not mask[:5].any()


# --- map keypoints ------------------------------------------------------------------------

KEYPOINT_REFINEMENT = RelocalizeOptions(refine="keypoints")  # the paper's refinement (the default is features)


def make_map(path: Path, keypoints: np.ndarray | None, metadata: dict | None = None) -> Path:
    torch.manual_seed(0)
    encoder = Encoder(width=0.25)
    torch.save(encoder.state_dict(), path.parent / "encoder.pt")
    head = Head(in_channels=encoder.out_channels, width=64)
    save_map(path, Regressor(encoder, head), metadata or {"short_side": 120, "median_depth": MEDIAN_DEPTH},
             keypoints_xyz=keypoints)
    return path


def test_map_keypoints_round_trip(tmp_path: Path):
    path = make_map(tmp_path / "map.pt", KEYPOINTS)
    payload = torch.load(path, weights_only=True)
    assert payload["keypoints_xyz"].dtype == torch.float32 and payload["keypoints_xyz"].shape == (10, 3)
    kp = map_keypoints(read_map_header(path))
    assert kp is not None and kp.dtype == np.float64 and kp.shape == (10, 3)
    assert np.allclose(kp, KEYPOINTS, atol=1e-6)
    assert map_keypoints(read_map_header(make_map(tmp_path / "plain.pt", None))) is None


@pytest.mark.parametrize(("bad", "match"), [
    (torch.zeros(5, 2), r"\(K,3\)"),
    (torch.zeros(5), r"\(K,3\)"),
    (torch.tensor([[0.0, 1.0, float("nan")]]), "non-finite"),
    ([[0.0, 1.0, 2.0]], "is a list"),
])
def test_malformed_map_keypoints_are_refused(tmp_path: Path, bad: object, match: str):
    path = make_map(tmp_path / "map.pt", KEYPOINTS)
    payload = torch.load(path, weights_only=True)
    payload["keypoints_xyz"] = bad
    broken = tmp_path / "broken.map.pt"
    torch.save(payload, broken)
    with pytest.raises(ModelError, match=match) as info:
        read_map_header(broken)
    assert "broken.map.pt" in str(info.value) and "\n" not in str(info.value)
    encoder = Encoder(width=0.25)
    with pytest.raises(ModelError, match="keypoints_xyz"):
        save_map(tmp_path / "x.pt", Regressor(encoder, Head(in_channels=encoder.out_channels, width=8)), {},
                 keypoints_xyz=np.zeros((4, 2)))
    assert not (tmp_path / "x.pt").exists()


# --- through the Relocalizer --------------------------------------------------------------

@pytest.fixture
def synthetic_query(monkeypatch: pytest.MonkeyPatch) -> np.ndarray:
    coords = coordinate_map((R_TRUE, T_TRUE), SMALL_BIAS)
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: coords.reshape(H_CELLS, W_CELLS, 3))
    return coords


def photo() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)


def test_relocalizer_refines_with_map_keypoints(tmp_path: Path, synthetic_query: np.ndarray):
    path = make_map(tmp_path / "map.pt", KEYPOINTS)
    est = Relocalizer(path, tmp_path / "encoder.pt", KEYPOINT_REFINEMENT).localize(photo(), CAM)
    assert est.success and est.refine_kept and est.refine_iterations >= 1
    assert errors(est.R, est.t)[0] < 1e-3 < 0.1 < errors(est.initial_R, est.initial_t)[0]
    assert est.inliers == 300
    out = est.to_json()
    assert out["refinement"]["kept"] is True and out["refinement"]["iterations"] == est.refine_iterations
    assert np.allclose(out["refinement"]["initial_t"], est.initial_t)
    assert set(out["seconds"]) == {"preprocess", "network", "pnp", "refine", "total"}

    off = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(refine="none")).localize(photo(), CAM)
    assert off.refine_iterations == 0 and not off.refine_kept
    assert np.array_equal(off.R, off.initial_R) and errors(off.R, off.t)[0] > 0.1
    assert np.allclose(off.R, est.initial_R)


def test_relocalizer_without_map_keypoints_warns_and_skips(tmp_path: Path, synthetic_query: np.ndarray,
                                                           caplog: pytest.LogCaptureFixture):
    path = make_map(tmp_path / "map.pt", None)
    with caplog.at_level(logging.WARNING, logger="usvc.relocalize.relocalizer"):
        reloc = Relocalizer(path, tmp_path / "encoder.pt", KEYPOINT_REFINEMENT)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "no 3D keypoints" in warnings[0].getMessage()
    est = reloc.localize(photo(), CAM)
    assert est.success and est.refine_iterations == 0 and not est.refine_kept
    assert np.array_equal(est.R, est.initial_R)


def test_write_results_records_refinement(tmp_path: Path, synthetic_query: np.ndarray):
    path = make_map(tmp_path / "map.pt", KEYPOINTS)
    est = Relocalizer(path, tmp_path / "encoder.pt", KEYPOINT_REFINEMENT).localize(photo(), CAM)
    nan_R, nan_t = np.full((3, 3), np.nan), np.full(3, np.nan)
    failed = PoseEstimate(False, nan_R, nan_t, 3, 300, {"preprocess": 0.0, "network": 0.1, "pnp": 0.2,
                                                        "total": 0.3})
    frames = [Frame(n, Path(n), CAM, "test", R_TRUE, T_TRUE) for n in ("a.png", "b.png")]
    stats = write_results(tmp_path, frames, [est, failed])
    with h5py.File(tmp_path / "queries.h5", "r") as h5:
        assert list(h5["refine_iterations"][()]) == [est.refine_iterations, 0]
        assert h5["refine_iterations"].dtype == np.int64 and h5["refine_kept"].dtype == bool
        assert list(h5["refine_kept"][()]) == [True, False]
        assert h5["initial_R"].shape == (2, 3, 3) and h5["initial_t"].shape == (2, 3)
        assert np.allclose(h5["initial_R"][0], est.initial_R) and np.isnan(h5["initial_R"][1]).all()
        assert np.allclose(h5["initial_t"][0], est.initial_t) and np.isnan(h5["initial_t"][1]).all()
    assert stats["refine_kept_fraction"] == 1.0  # over the queries that localized
    assert stats["refine_mean_iterations"] == float(est.refine_iterations)
    assert stats["ms_refine"] == pytest.approx(est.seconds["refine"] * 500)
