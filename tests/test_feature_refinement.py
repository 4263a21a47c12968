"""Refinement by features: landmarks from SfM tracks, guided matching from the learned pose, the
fallback to matching every landmark, and how the relocalizer finds, checks and reports them.

The synthetic scene: 3D points on a smooth surface in front of a known camera, each with a
random unit descriptor (its landmark); the query's keypoints are the visible points' projections
plus 0.3 px noise, with their descriptors slightly perturbed, and as many distractor keypoints
with unrelated descriptors. Exact matches then pin the pose far below the prior's error.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_refinement import CAM, KEYPOINTS, R_TRUE, T_TRUE, backproject, errors, make_map, photo, synthetic_query  # noqa: F401

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.landmarks.build import build_landmarks
from usvc.landmarks.landmark_table import Landmarks, encode_descriptors, unit_descriptors
from usvc.landmarks.landmarks_file import landmarks_disagree, read_landmarks, write_landmarks
from usvc.landmarks.options import LandmarksOptions
from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.features.byte_products import ByteRows, int8_products, scaled
from usvc.relocalize.features.matching import global_matches, guided_matches
from usvc.relocalize.features.passes import FeatureMatchOptions, feature_options, visible_landmarks
from usvc.relocalize.features.path import refine_by_features
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer
from usvc.sfm.tracks_file import Tracks

OPTS = FeatureMatchOptions(radii_px=(24.0, 6.0, 2.0), ratio=0.8, max_error_px=1.5, min_inliers=12,
                           view_margin_deg=45.0)
N_POINTS = 400


def scene(seed: int = 0) -> tuple[Landmarks, QueryFeatures]:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([4, 4], [CAM.width - 4, CAM.height - 4], (N_POINTS, 2))
    xyz = backproject(uv, R_TRUE, T_TRUE)
    desc = unit_descriptors(rng.random((N_POINTS, 128)) ** 4)  # sparse-ish, SIFT-like positive rows
    center = -R_TRUE.T @ T_TRUE
    view = center - xyz
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    landmarks = Landmarks("synthetic", xyz, encode_descriptors(desc), view.astype(np.float32),
                          np.full(N_POINTS, 5.0, np.float32), np.full(N_POINTS, 3, np.int32), 120)
    noisy = unit_descriptors(desc + 0.02 * rng.random(desc.shape))
    distract_uv = rng.uniform([0, 0], [CAM.width, CAM.height], (N_POINTS, 2))
    distract = unit_descriptors(rng.random((N_POINTS, 128)) ** 4)
    feats = QueryFeatures(np.concatenate([uv + rng.normal(0, 0.3, uv.shape), distract_uv]),
                          np.concatenate([noisy, distract]).astype(np.float32))
    return landmarks, feats


def prior(rot_deg: float, shift_frac: float) -> tuple[np.ndarray, np.ndarray]:
    """The true pose turned by rot_deg and moved by shift_frac of the median depth (2.0)."""
    R = Rotation.from_rotvec(np.radians(rot_deg) * np.array([0.0, 1.0, 0.0])).as_matrix() @ R_TRUE
    return R, T_TRUE + np.array([shift_frac * 2.0, 0.0, 0.0])


def test_guided_matching_finds_the_exact_pose_from_a_perturbed_prior():
    landmarks, feats = scene()
    R0, t0 = prior(5.0, 0.10)
    assert errors(R0, t0)[0] > 4.0  # the prior is 5 deg off
    out = refine_by_features(landmarks, scaled(landmarks.descriptor), feats, CAM, R0, t0, OPTS)
    assert out.success and out.path == "guided"
    rot, trans = errors(out.R, out.t)
    assert rot < 0.1 and trans < 0.005  # 0.3 px keypoint noise over ~400 matches
    assert out.inliers >= 0.8 * N_POINTS
    assert [p["kind"] for p in out.passes] == ["guided"] * 3
    assert [p["radius_px"] for p in out.passes] == list(OPTS.radii_px)


def test_a_prior_outside_the_radius_falls_back_to_matching_every_landmark():
    landmarks, feats = scene()
    R0, t0 = prior(40.0, 0.5)  # projections land far outside 24 px
    out = refine_by_features(landmarks, scaled(landmarks.descriptor), feats, CAM, R0, t0, OPTS)
    assert out.success and out.path == "global"
    assert out.passes[0]["kind"] == "guided" and out.passes[0]["inliers"] == 0
    assert out.passes[1]["kind"] == "global"
    rot, trans = errors(out.R, out.t)
    assert rot < 0.1 and trans < 0.005
    # no prior at all: straight to the global match
    none = refine_by_features(landmarks, scaled(landmarks.descriptor), feats, CAM, None, None, OPTS)
    assert none.success and none.path == "global" and none.passes[0]["kind"] == "global"


def mislead_the_guided_passes(monkeypatch) -> None:
    """From now on the guided passes settle on a pose 3 deg off, with a fifth of the support."""
    from usvc.relocalize.features import path as fr  # where refine_by_features calls the guided passes

    real = fr.from_prior

    def misled(*args, **kwargs):
        out = real(*args, **kwargs)
        out.R, out.inliers = prior(3.0, 0.0)[0], out.inliers // 5
        return out

    monkeypatch.setattr(fr, "from_prior", misled)


def test_a_weak_prior_also_gets_the_matches_to_every_landmark(monkeypatch):
    """A learned pose too few cells agree with may lead the guided passes to a wrong pose with some
    support: with `weak_prior` the matches to every landmark are tried too and the better-supported
    pose wins; the verified evidence is not asked for (the guided passes found a pose)."""
    landmarks, feats = scene()
    R0, t0 = prior(5.0, 0.10)
    desc = scaled(landmarks.descriptor)
    mislead_the_guided_passes(monkeypatch)
    asked = []
    strong = refine_by_features(landmarks, desc, feats, CAM, R0, t0, OPTS, verified=lambda: asked.append(1))
    assert strong.path == "guided" and errors(strong.R, strong.t)[0] > 2.0
    assert [h["path"] for h in strong.tried] == ["guided"]
    weak = refine_by_features(landmarks, desc, feats, CAM, R0, t0, OPTS, verified=lambda: asked.append(1),
                              weak_prior=True)
    assert weak.path == "global" and errors(weak.R, weak.t)[0] < 0.1
    assert [h["path"] for h in weak.tried] == ["guided", "global"] and asked == []


def test_no_pose_from_features_of_another_scene():
    landmarks, _ = scene(0)
    _, other = scene(1)  # same layout, unrelated descriptors
    out = refine_by_features(landmarks, scaled(landmarks.descriptor), other, CAM, *prior(5.0, 0.1), OPTS)
    assert not out.success and out.path == "" and "no pose" in out.why
    assert out.R is None and out.t is None


def test_guided_matches_stay_within_the_radius_and_are_one_to_one():
    landmarks, feats = scene()
    idx, uv = visible_landmarks(landmarks, CAM, R_TRUE, T_TRUE, 45.0)
    assert len(idx) == N_POINTS
    li, ki = guided_matches(uv, scaled(landmarks.descriptor)[idx], feats, 3.0, 0.8)
    assert len(li) > 0.9 * N_POINTS
    assert np.all(np.linalg.norm(uv[li] - feats.uv[ki], axis=1) <= 3.0)
    assert len(set(ki.tolist())) == len(ki)
    assert np.mean(idx[li] == ki) > 0.99  # keypoint k of the first N_POINTS is landmark k
    gl, gk = global_matches(scaled(landmarks.descriptor), feats, 0.8)
    assert len(gl) > 0.9 * N_POINTS and np.mean(gl == gk) > 0.99


def _reference_guided(lm_uv, lm_desc, feats, radius, ratio):
    """Guided matching as its definition reads, on the full matrices: per landmark, the nearest
    keypoint within the radius (the first on ties), ratio test, then one landmark per keypoint."""
    sim = lm_desc @ feats.scaled.T
    near = np.linalg.norm(lm_uv[:, None] - feats.uv[None], axis=2) <= radius
    rows, cols, dist = [], [], []
    for i in range(len(lm_uv)):
        s = np.where(near[i], sim[i], -np.inf)
        j = int(np.argmax(s))
        if not np.isfinite(s[j]):
            continue
        s2 = np.max(np.delete(s, j))
        d1, d2 = np.sqrt(max(2 - 2 * s[j], 0)), np.sqrt(max(2 - 2 * s2, 0)) if np.isfinite(s2) else np.inf
        if d1 < ratio * d2:
            rows.append(i), cols.append(j), dist.append(d1)
    keep = [k for k in range(len(rows)) if all(dist[k] < dist[m] or (dist[k] == dist[m] and k < m)
                                               for m in range(len(rows)) if cols[m] == cols[k] and m != k)]
    return np.array([rows[k] for k in keep], np.int64), np.array([cols[k] for k in keep], np.int64)


def _reference_global(lm_desc, feats, ratio):
    """Matching against every landmark as its definition reads: nearest, ratio test, mutual."""
    sim = feats.scaled @ lm_desc.T
    best = np.argmax(sim, axis=1)
    top2 = -np.sort(-sim, axis=1)[:, :2]
    d = np.sqrt(np.maximum(2 - 2 * top2, 0))
    ok = (d[:, 0] < ratio * d[:, 1]) & (np.argmax(sim, axis=0)[best] == np.arange(len(sim)))
    cols = np.flatnonzero(ok)
    return best[cols], cols


CUDA_MARKS = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")]


# tile_cost 0: never tiles; 10**9: tiles wherever the CPU matches (device None). dense_share 0: the
# pairs' own descriptors; 10**9: one product on the device. device: the products with numpy (None,
# the CPU default) or torch on that device (`usvc.relocalize.features.device_matching`)
@pytest.mark.parametrize("tile_cost,dense_share,device", [(0, 0, None), (10**9, 0, None), (0, 10**9, "cpu"),
                                                           pytest.param(0, 10**9, "cuda", marks=CUDA_MARKS)])
def test_guided_and_global_matching_are_their_definitions(tile_cost: float, dense_share: int, device: str | None,
                                                          monkeypatch):
    from usvc.relocalize.features import device_matching, matching, tiled_matching
    monkeypatch.setattr(matching, "_TILE_PAIR_COST", tile_cost)
    monkeypatch.setattr(matching, "_DENSE_PAIR_SHARE", dense_share)
    monkeypatch.setattr(tiled_matching, "MAX_TILES", 12)  # tiles wider than the smaller radii
    monkeypatch.setattr(matching, "_CHUNK", 96)  # several blocks of landmarks
    monkeypatch.setattr(device_matching, "_CHUNK_ENTRIES", 96 * 700)  # the same on a device
    monkeypatch.setattr(matching, "_PAIRS", 500)  # several blocks of pairs
    landmarks, feats = scene(3)
    desc = scaled(landmarks.descriptor)
    R, t = prior(2.0, 0.02)  # off the true pose: landmarks project a few px from their keypoints
    idx, uv = visible_landmarks(landmarks, CAM, R, t, 45.0)
    for radius in (1.0, 4.0, 12.0, 40.0):
        got, want = (guided_matches(uv, desc[idx], feats, radius, 0.8, device),
                     _reference_guided(uv, desc[idx], feats, radius, 0.8))
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), radius
    # a second, noisier keypoint for 50 landmarks: its nearest landmark is the first one's, so only
    # the mutual check keeps it out
    rng = np.random.default_rng(4)
    twins = QueryFeatures(np.concatenate([feats.uv, feats.uv[:50] + 1.0]), np.concatenate(
        [feats.descriptor, unit_descriptors(feats.descriptor[:50] + 0.03 * rng.random((50, 128)))]).astype(np.float32))
    got, want = global_matches(desc, twins, 0.8, device), _reference_global(desc, twins, 0.8)
    assert len(want[0]) > N_POINTS / 2 and len(np.unique(want[0])) == len(want[0])
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    if device is None:  # the bytes' own products (int8 where the CPU has them, float32 of the bytes): the same
        for int8 in (False, True) if int8_products() else (False,):
            got = global_matches(desc, twins, 0.8, None, ByteRows.of(landmarks.descriptor, int8))
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), int8


def test_visible_landmarks_are_their_definition():
    """In front, inside the image, and seen from within the mapped cone widened by the margin: the
    same landmarks and pixels as each test applied to every landmark, on a map where each test
    removes some (behind the camera, outside the image, seen from too far aside)."""
    from usvc.relocalize.pnp import project_points

    rng = np.random.default_rng(7)
    n = 3000
    xyz = rng.normal(0.0, 2.0, (n, 3)) + (-R_TRUE.T @ T_TRUE) + 2.0 * R_TRUE[2]  # around the view, some behind
    view = rng.normal(0.0, 1.0, (n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    cone = rng.uniform(0.0, 120.0, n).astype(np.float32)
    landmarks = Landmarks("synthetic", xyz, np.zeros((n, 128), np.uint8), view.astype(np.float32), cone,
                          np.full(n, 2, np.int32), 120)
    uv, depth = project_points(CAM, xyz, R_TRUE, T_TRUE)
    inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= CAM.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= CAM.height)
    ray = (-R_TRUE.T @ T_TRUE)[None] - xyz
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(ray * landmarks.view_dir, axis=1), -1.0, 1.0)))
    for margin in (0.0, 45.0, 180.0):
        want = np.flatnonzero(inside & (angle <= np.minimum(cone + margin, 180.0)))
        idx, got_uv = visible_landmarks(landmarks, CAM, R_TRUE, T_TRUE, margin)
        assert np.array_equal(idx, want) and np.array_equal(got_uv, uv[want]), margin
        assert 0 < len(idx) < inside.sum() or margin == 180.0
    assert 0 < inside.sum() < n


def test_landmarks_behind_or_seen_from_the_other_side_are_not_candidates():
    landmarks, _ = scene()
    flipped = Landmarks("synthetic", landmarks.xyz, landmarks.descriptor, -landmarks.view_dir,
                        landmarks.view_angle_deg, landmarks.track_length, 120)
    assert len(visible_landmarks(flipped, CAM, R_TRUE, T_TRUE, 45.0)[0]) == 0
    away = Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix() @ R_TRUE  # same centre, looking back
    t_away = -away @ (-R_TRUE.T @ T_TRUE)
    assert len(visible_landmarks(landmarks, CAM, away, t_away, 180.0)[0]) == 0


def tracks_of(landmarks: Landmarks) -> Tracks:
    """Tracks with two observations per point (cameras at the true pose), descriptors as given."""
    n = len(landmarks)
    obs_desc = np.repeat(landmarks.descriptor, 2, axis=0)
    return Tracks(image_names=["a.jpg", "b.jpg"], R=np.stack([R_TRUE, R_TRUE]),
                  t=np.stack([T_TRUE, T_TRUE + [0.1, 0, 0]]), K=np.stack([CAM.K, CAM.K]),
                  point_id=np.arange(n), xyz=landmarks.xyz, rgb=np.zeros((n, 3), np.uint8),
                  error=np.full(n, 0.5, np.float32), offset=np.arange(0, 2 * n + 1, 2),
                  obs_image=np.tile([0, 1], n).astype(np.int32), obs_uv=np.zeros((2 * n, 2), np.float32),
                  obs_descriptor=obs_desc, obs_error=np.full(2 * n, 0.5, np.float32))


@pytest.mark.parametrize("how", ["mean", "medoid"])
def test_build_landmarks_keeps_points_and_descriptors(how: str, tmp_path: Path):
    landmarks, _ = scene()
    built = build_landmarks(tracks_of(landmarks), "synthetic", 120, LandmarksOptions(descriptor=how))
    assert np.array_equal(built.xyz, landmarks.xyz)  # the SfM points bit for bit
    assert np.abs(built.descriptor.astype(int) - landmarks.descriptor.astype(int)).max() <= 1
    assert np.all(built.view_angle_deg < 10) and np.allclose(np.linalg.norm(built.view_dir, axis=1), 1, atol=1e-5)
    write_landmarks(tmp_path / LANDMARKS_H5, built)
    back = read_landmarks(tmp_path / LANDMARKS_H5)
    assert back.scene == "synthetic" and back.image_short_side == 120
    assert np.array_equal(back.xyz, built.xyz) and np.array_equal(back.descriptor, built.descriptor)
    few = build_landmarks(tracks_of(landmarks), "synthetic", 120, LandmarksOptions(max_landmarks=50))
    assert len(few) == 50
    with pytest.raises(UsvcError, match="qualify as landmarks"):
        build_landmarks(tracks_of(landmarks), "synthetic", 120, LandmarksOptions(min_track_length=3))


def test_landmarks_of_another_scene_are_refused(tmp_path: Path):
    landmarks, _ = scene()
    assert landmarks_disagree(landmarks, "synthetic", landmarks.xyz[:10]) == ""
    assert "of scene 'synthetic', the map of 'office'" in landmarks_disagree(landmarks, "office", None)
    assert "another SfM model" in landmarks_disagree(landmarks, "synthetic", landmarks.xyz[:10] + 1e-3)
    # a map whose keypoints are not among the landmarks beside it: refused, one line, naming both
    path = make_map(tmp_path / "map.pt", KEYPOINTS, {"short_side": 120, "median_depth": 2.0, "scene": "synthetic"})
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    with pytest.raises(UsvcError, match="are not the landmarks of map") as info:
        Relocalizer(path, tmp_path / "encoder.pt")
    assert "\n" not in str(info.value) and "map.pt" in str(info.value)


def test_relocalizer_refines_by_features_and_reports_the_path(tmp_path: Path, synthetic_query, monkeypatch):
    landmarks, feats = scene()
    (tmp_path / "map").mkdir()
    (tmp_path / "landmarks").mkdir()
    path = make_map(tmp_path / "map" / "map.pt", landmarks.xyz[:10].astype(np.float32),
                    {"short_side": 120, "median_depth": 2.0, "scene": "synthetic"})
    write_landmarks(tmp_path / "landmarks" / LANDMARKS_H5, landmarks)  # the pipeline's layout
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: feats)
    reloc = Relocalizer(path, tmp_path / "map" / "encoder.pt")
    assert reloc.landmarks_path == tmp_path / "landmarks" / LANDMARKS_H5
    est = reloc.localize(photo(), CAM)
    assert est.success and est.refine_path == "guided" and est.feature_inliers >= 0.8 * N_POINTS
    assert errors(est.R, est.t)[0] < 0.1 < errors(est.initial_R, est.initial_t)[0]
    rec = est.to_json()["refinement"]
    assert rec["method"] == "features" and rec["path"] == "guided" and rec["learned_pose_kept"] is False
    assert rec["feature_inliers"] == est.feature_inliers and len(rec["passes"]) == 3
    # the same map with refine=none: the learned pose, untouched
    plain = Relocalizer(path, tmp_path / "map" / "encoder.pt", RelocalizeOptions(refine="none")).localize(photo(), CAM)
    assert plain.refine_path == "dense" and np.allclose(plain.R, est.initial_R)


def test_features_from_another_place_fall_back_to_the_dense_answer(tmp_path: Path, synthetic_query, monkeypatch):
    landmarks, _ = scene(0)
    _, other = scene(1)
    make_map(tmp_path / "map.pt", landmarks.xyz[:10].astype(np.float32),
             {"short_side": 120, "median_depth": 2.0, "scene": "synthetic"})
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: other)
    est = Relocalizer(tmp_path / "map.pt", tmp_path / "encoder.pt").localize(photo(), CAM)
    assert est.refine_path == "dense" and est.feature_inliers == 0
    assert est.to_json()["refinement"]["learned_pose_kept"] is True
    assert est.to_json()["refinement"]["passes"][-1]["kind"] == "global"


def test_a_map_without_landmarks_localizes_with_one_note(tmp_path: Path, synthetic_query,
                                                         caplog: pytest.LogCaptureFixture):
    make_map(tmp_path / "map.pt", KEYPOINTS)
    with caplog.at_level(logging.WARNING, logger="usvc.relocalize.relocalizer"):
        reloc = Relocalizer(tmp_path / "map.pt", tmp_path / "encoder.pt")
    notes = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(notes) == 1 and "refinement by features is off" in notes[0]
    est = reloc.localize(photo(), CAM)
    assert est.success and est.refine_path == "dense" and est.to_json()["refinement"]["method"] == "none"


def test_feature_radii_scale_with_the_image():
    opts = feature_options(RelocalizeOptions(features_radii_px=[96.0, 24.0], features_max_error_px=6.0), 240)
    assert opts.radii_px == (48.0, 12.0) and opts.max_error_px == 3.0


@pytest.mark.parametrize(("key", "value"), [("refine", "yes"), ("features_extractor", "orb"),
                                            ("features_ratio", 1.5), ("features_min_inliers", 3),
                                            ("features_radii_px", []), ("features_radii_px", [8.0, -1.0])])
def test_bad_feature_options_are_named(key: str, value: object):
    problems = RelocalizeOptions(**{key: value}).problems()
    assert len(problems) == 1 and problems[0].startswith(f"{key}=")


def synthetic_relocalizer(tmp_path: Path, monkeypatch) -> tuple[Relocalizer, QueryFeatures]:
    """A relocalizer on a map of `scene()`'s landmarks, whose query photos have `scene()`'s features
    (with `synthetic_query`'s coordinates): the relocalizer and those features."""
    landmarks, feats = scene()
    make_map(tmp_path / "map.pt", landmarks.xyz[:10].astype(np.float32),
             {"short_side": 120, "median_depth": 2.0, "scene": "synthetic"})
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: feats)
    return Relocalizer(tmp_path / "map.pt", tmp_path / "encoder.pt"), feats


def test_a_wrong_focal_length_is_refused_by_the_features(tmp_path: Path, synthetic_query, monkeypatch):
    reloc, _ = synthetic_relocalizer(tmp_path, monkeypatch)
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    for factor in (2.0, 0.5):
        est = reloc.localize(photo(), (fx * factor, fy * factor, cx, cy))
        assert not est.success and "focal length" in est.rejected, (factor, est.rejected)
        assert np.isnan(est.R).all()
    assert reloc.localize(photo(), (fx * 1.1, fy * 1.1, cx, cy)).rejected == ""  # within the 25 % tolerance


def test_without_intrinsics_the_features_estimate_the_focal_and_refuse_a_stretched_photo(
        tmp_path: Path, synthetic_query, monkeypatch):
    """No intrinsics: the photo's matches to every landmark give the focal length (P4Pf), and a
    photo stretched to another aspect ratio (keypoints 1.5x wider about the centre) is refused
    by what those matches say, not answered with a pose tens of degrees off."""
    reloc, feats = synthetic_relocalizer(tmp_path, monkeypatch)
    est = reloc.localize(photo(), None)
    assert est.success and est.refine_path == "guided" and est.focal_estimated
    assert abs(est.camera.params[0] / CAM.focal[0] - 1.0) < 0.25  # the features' focal, not the 1.2 x side prior
    cx = CAM.principal_point[0]
    wide = QueryFeatures(np.c_[cx + 1.5 * (feats.uv[:, 0] - cx), feats.uv[:, 1]], feats.descriptor)
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: wide)
    est = reloc.localize(photo(), None)
    assert not est.success and "looks stretched" in est.rejected and np.isnan(est.R).all()


def test_descriptor_products_go_to_the_device_only_off_the_cpu():
    """On the CPU the relocalizer keeps numpy's products (the measured answers); on a GPU, torch's there."""
    from usvc.relocalize.features.device_matching import matching_device

    assert matching_device("cpu") is None
    assert matching_device("cuda") == "cuda" and matching_device("cuda:1") == "cuda:1"


def test_a_relocalizer_on_a_device_matches_there_and_answers_as_on_the_cpu(tmp_path: Path, synthetic_query,
                                                                            monkeypatch):
    """The device path of the relocalizer (forced here onto torch's CPU: the same code as on a GPU)
    computes its products through `device_matching` and gives the CPU's answers."""
    from usvc.relocalize.features import device_matching, matching
    from usvc.relocalize.features import path as path_module

    reloc, _ = synthetic_relocalizer(tmp_path, monkeypatch)
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    queries = [(fx, fy, cx, cy), (2 * fx, 2 * fy, cx, cy), None]
    on_cpu = [reloc.localize(photo(), q) for q in queries]
    calls = []
    for name in ("masked_row_best_two", "best_two_and_column_max"):
        real = getattr(device_matching, name)
        monkeypatch.setattr(matching, name,
                            lambda *a, _real=real, _name=name: calls.append(_name) or _real(*a))
    # where the matching against every landmark, and the guided passes, are placed
    monkeypatch.setattr(path_module, "matching_device", lambda device: "cpu")
    on_device = [reloc.localize(photo(), q) for q in queries]
    assert {"masked_row_best_two", "best_two_and_column_max"} <= set(calls)
    for a, b in zip(on_cpu, on_device):
        assert a.success == b.success and a.rejected == b.rejected and a.refine_path == b.refine_path
        if a.success:
            assert np.allclose(a.R, b.R, atol=1e-9) and np.allclose(a.t, b.t, atol=1e-9)
