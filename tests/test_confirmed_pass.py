"""The default last pass of refinement by features (relocalize.features_final=confirmed): each of
the answer's own matches weighted by the mapping images whose SIFT + PnP matching finds the same
(keypoint site, landmark) pair, unconfirmed matches dropped, the pose refined on the rest.

On the synthetic scene of test_fallback (five mapping cameras, every observation its own noisy
descriptor)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_fallback import MAPPING, N_POINTS, WRONG, _map, scene
from test_refinement import CAM, R_TRUE, T_TRUE, errors, photo

from usvc.relocalize.features import last_pass as last_pass_module
from usvc.relocalize.features.last_pass import confirmations, confirmed_pass, keypoint_sites
from usvc.relocalize.features.passes import VERIFIED_MAX_ERROR_PX, FeatureResult, accept, feature_options
from usvc.relocalize.features.verified_matching import observation_descriptors
from usvc.relocalize.options import RelocalizeOptions
from usvc.relocalize.pnp import PnPResult
from usvc.relocalize.relocalizer import Relocalizer

pytestmark = pytest.mark.precision  # the Relocalizer runs the network at `auto`: CI runs these under both


def test_confirmations_count_each_pair_once_per_correspondence():
    found_kp = np.array([3, 3, 3, 5, 5, 7])
    found_lm = np.array([10, 10, 11, 20, 20, 30])
    # (3, 10) twice, (3, 11) once, (5, 20) twice, (7, 30) once; (7, 31) and (9, 10) never
    got = confirmations(np.array([3, 3, 5, 7, 7, 9]), np.array([10, 11, 20, 30, 31, 10]), found_kp, found_lm)
    assert got.tolist() == [2, 1, 2, 1, 0, 0]
    assert confirmations(np.array([1]), np.array([2]), np.zeros(0, np.int64), np.zeros(0, np.int64)).tolist() == [0]
    assert confirmations(np.zeros(0, np.int64), np.zeros(0, np.int64), found_kp, found_lm).tolist() == []
    # a landmark row beyond every found one is no match, however the keys are packed
    assert confirmations(np.array([0]), np.array([10 ** 6]), found_kp, found_lm).tolist() == [0]


def test_keypoint_sites_join_the_orientations_of_one_location():
    uv = np.array([[5.0, 6.0], [1.0, 2.0], [5.0, 6.0], [5.0, 6.5], [1.0, 2.0]])
    assert keypoint_sites(uv).tolist() == [0, 1, 0, 3, 1]
    assert keypoint_sites(np.zeros((0, 2))).tolist() == []


def _answer(landmarks, feats, keypoint: np.ndarray, rows: np.ndarray) -> FeatureResult:
    """A guided answer at the true pose found with these matches."""
    out = FeatureResult(None, None, path="guided")
    accept(out, PnPResult(True, R_TRUE, T_TRUE, np.ones(len(rows), bool), len(rows), 0.0), feats, keypoint,
            landmarks, rows)
    return out


def test_unconfirmed_matches_are_dropped_and_confirmed_ones_weighted_by_their_images():
    """Right matches are confirmed by the mapping images that see them; a wrong match that the
    pose still explains (a distractor keypoint beside the landmark) is confirmed by none, so it
    takes no part in the refinement; the record says how many were confirmed, and how often."""
    landmarks, feats = scene()
    opts = feature_options(RelocalizeOptions(), CAM.height)
    right = np.arange(N_POINTS)
    out = _answer(landmarks, feats, right, right)
    confirmed_pass(out, landmarks, feats, CAM, opts, observation_descriptors(landmarks.observations))
    record = out.passes[-1]
    assert record["kind"] == "confirmed" and record["candidates"] == len(MAPPING)
    assert record["confirmed"] >= 0.9 * N_POINTS and record["inliers"] == record["confirmed"]
    assert record["confirmations"] <= record["confirmed"] * len(MAPPING)
    assert record["confirmations"] >= 2 * record["confirmed"]  # most points are seen in several images
    rot, trans = errors(out.R, out.t)
    assert rot < 0.2 and trans < 0.01  # the keypoints' 0.3 px noise: ~0.1 deg here

    # 40 landmarks given to distractor keypoints moved onto their projection: the pose explains them,
    # their descriptors are another point's, so no image confirms them
    wrong = np.arange(40)
    moved = feats.uv.copy()
    moved[N_POINTS + wrong] = moved[wrong] + 0.5
    feats = replace(feats, uv=moved)
    keypoint = np.concatenate([right[40:], N_POINTS + wrong])
    out = _answer(landmarks, feats, keypoint, np.concatenate([right[40:], wrong]))
    confirmed_pass(out, landmarks, feats, CAM, opts, observation_descriptors(landmarks.observations))
    assert out.passes[-1]["confirmed"] <= N_POINTS - 40
    assert not np.isin(out.match_keypoint, N_POINTS + wrong).any()  # the answer's matches: confirmed ones only
    assert len(out.match_keypoint) == out.passes[-1]["confirmed"] and out.inliers == out.passes[-1]["inliers"]


def test_too_few_confirmed_matches_keep_the_answer():
    """A pass that confirms fewer than min_inliers matches changes nothing but its record."""
    landmarks, feats = scene()
    opts = feature_options(RelocalizeOptions(features_min_inliers=20), CAM.height)
    few = np.arange(10)
    out = _answer(landmarks, feats, few, few)
    before = (out.R.copy(), out.t.copy(), out.inliers, out.match_keypoint.copy())
    confirmed_pass(out, landmarks, feats, CAM, opts, observation_descriptors(landmarks.observations))
    assert out.passes[-1]["kind"] == "confirmed" and out.passes[-1]["inliers"] == 0
    assert np.array_equal(out.R, before[0]) and np.array_equal(out.t, before[1]) and out.inliers == before[2]
    assert np.array_equal(out.match_keypoint, before[3])


@pytest.mark.parametrize("learned", ["right", "wrong"])
def test_the_default_ends_with_the_confirmed_pass(tmp_path: Path, monkeypatch, learned: str):
    """The default last pass is the confirmed one, after the guided or global path (not after SIFT +
    PnP's own path, whose matches are that evidence already); features_final=guided does not run it;
    the path that found the photo is the same either way."""
    assert RelocalizeOptions().features_final == "confirmed"
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE) if learned == "right" else WRONG)
    default = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    guided = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(features_final="guided")).localize(photo(),
                                                                                                          CAM)
    kinds = [p["kind"] for p in default.to_json()["refinement"]["passes"]]
    assert "confirmed" not in [p["kind"] for p in guided.to_json()["refinement"]["passes"]]
    assert default.success and guided.success and default.refine_path == guided.refine_path, default.rejected
    if default.refine_path == "verified":
        assert "confirmed" not in kinds
    else:
        assert kinds[-1] == "confirmed"
        assert default.to_json()["refinement"]["passes"][-1]["confirmed"] >= 0.8 * N_POINTS
    rot, trans = errors(default.R, default.t)
    assert rot < 0.2 and trans < 0.01


def test_a_pose_a_few_pixels_off_is_confirmed_and_corrected(monkeypatch):
    """The pass confirms the guided matches of a pose ~6 px off (its check is CONFIRM_MAX_ERROR_PX,
    8 px, not SIFT + PnP's 4) and refines it onto the truth; at 4 px the same answer confirms almost
    nothing and is kept as it was."""
    landmarks, feats = scene()
    # the answer's inliers, which choose the images, at the guided threshold of a 480 px image (7.5 px here)
    opts = feature_options(RelocalizeOptions(features_max_error_px=30.0), CAM.height)
    right = np.arange(N_POINTS)
    turn = Rotation.from_rotvec([0.0, 6.0 / CAM.focal[0], 0.0]).as_matrix()  # about the camera centre: ~6 px
    R_off, off = turn @ R_TRUE, turn @ T_TRUE

    def answer() -> FeatureResult:
        out = FeatureResult(None, None, path="guided")
        accept(out, PnPResult(True, R_off, off, np.ones(N_POINTS, bool), N_POINTS, 0.0), feats, right, landmarks,
                right)
        return out

    out = answer()
    confirmed_pass(out, landmarks, feats, CAM, opts, observation_descriptors(landmarks.observations))
    assert out.passes[-1]["confirmed"] >= 0.8 * N_POINTS
    rot, trans = errors(out.R, out.t)
    assert rot < 0.2 < errors(R_off, off)[0] and trans < 0.01
    monkeypatch.setattr(last_pass_module, "CONFIRM_MAX_ERROR_PX", VERIFIED_MAX_ERROR_PX)
    out = answer()
    confirmed_pass(out, landmarks, feats, CAM, opts, observation_descriptors(landmarks.observations))
    assert out.passes[-1]["confirmed"] < 0.2 * N_POINTS and np.array_equal(out.t, off)
