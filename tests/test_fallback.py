"""When the learned pose is wrong, SIFT + PnP's evidence still localizes the photo: the query's
keypoints matched to each mapping image's observed keypoints, verified per pair, lifted through the
tracks (landmarks.h5's observations), LO-RANSAC PnP, then guided passes; and no check on the
learned pose refuses a photo before the features have run.

The synthetic scene of test_feature_refinement (points on a smooth surface, random SIFT-like
descriptors), now seen by five mapping cameras around the query's, each observation with its own
slightly perturbed descriptor, so the landmarks carry real tracks and verification sees real
two-view geometry.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_refinement import CAM, R_TRUE, T_TRUE, backproject, coordinate_map, errors, make_map, photo

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.landmarks.build import build_landmarks
from usvc.landmarks.landmark_table import Landmarks, encode_descriptors, unit_descriptors
from usvc.landmarks.landmarks_file import read_landmarks, write_landmarks
from usvc.landmarks.options import LandmarksOptions
from usvc.relocalize import query_cores
from usvc.relocalize import relocalizer as relocalizer_module
from usvc.relocalize.features import evidence as evidence_module
from usvc.relocalize.features import path as path_module
from usvc.relocalize.features import sift as sift_module
from usvc.relocalize.features.path import FeaturePath
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import (
    MIN_PAIR_INLIERS,
    pose_checked_matches,
    verified_matches,
)
from usvc.relocalize.pnp import project_points, refine_on_inliers, solve_pnp
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer
from usvc.sfm.tracks_file import Tracks

pytestmark = pytest.mark.precision  # what `auto` resolves to matters here: CI runs these under both

N_POINTS = 400
META = {"short_side": 120, "median_depth": 2.0, "scene": "synthetic"}
# Five mapping cameras: the query's pose moved sideways and turned a little (a capture around it).
MAPPING = [(Rotation.from_rotvec(r).as_matrix() @ R_TRUE, T_TRUE + np.array(d)) for r, d in [
    ([0.0, 0.05, 0.0], [-0.25, 0.0, 0.0]), ([0.0, -0.05, 0.0], [0.25, 0.0, 0.0]),
    ([0.04, 0.0, 0.0], [0.0, -0.2, 0.05]), ([-0.04, 0.0, 0.0], [0.0, 0.2, -0.05]),
    ([0.0, 0.0, 0.08], [0.1, 0.1, 0.1])]]
# A learned pose far from the truth (35 deg, a metre off): the guided pass finds nothing from it.
WRONG = (Rotation.from_rotvec([0.0, 0.6, 0.0]).as_matrix() @ R_TRUE, T_TRUE + np.array([1.0, 0.0, 0.2]))


def _tracks(xyz: np.ndarray, desc: np.ndarray, rng: np.random.Generator) -> Tracks:
    """Every point's observations in the mapping cameras that see it, each with its own noisy descriptor."""
    point, image, uv, descs = [], [], [], []
    for m, (R, t) in enumerate(MAPPING):
        p, depth = project_points(CAM, xyz, R, t)
        seen = np.flatnonzero((depth > 0) & (p[:, 0] > 1) & (p[:, 0] < CAM.width - 1)
                              & (p[:, 1] > 1) & (p[:, 1] < CAM.height - 1))
        point.append(seen)
        image.append(np.full(len(seen), m, np.int32))
        uv.append(p[seen] + rng.normal(0, 0.3, (len(seen), 2)))
        descs.append(encode_descriptors(unit_descriptors(desc[seen] + 0.02 * rng.random((len(seen), 128)))))
    point = np.concatenate(point)
    order = np.argsort(point, kind="stable")
    counts = np.bincount(point, minlength=len(xyz))
    assert counts.min() >= 2  # every point is a landmark
    n, obs = len(xyz), len(point)
    return Tracks(image_names=[f"m{m}.png" for m in range(len(MAPPING))], R=np.stack([r for r, _ in MAPPING]),
                  t=np.stack([t for _, t in MAPPING]), K=np.stack([CAM.K] * len(MAPPING)), point_id=np.arange(n),
                  xyz=xyz, rgb=np.zeros((n, 3), np.uint8), error=np.full(n, 0.5, np.float32),
                  offset=np.r_[0, np.cumsum(counts)], obs_image=np.concatenate(image)[order],
                  obs_uv=np.concatenate(uv)[order].astype(np.float32), obs_descriptor=np.concatenate(descs)[order],
                  obs_error=np.full(obs, 0.5, np.float32))


def scene(seed: int = 0) -> tuple[Landmarks, QueryFeatures]:
    """Landmarks with observations, and the query's features (true projections plus as many distractors)."""
    _, landmarks, feats = scene_and_tracks(seed)
    return landmarks, feats


def scene_and_tracks(seed: int = 0, more: Callable[[Tracks, np.random.Generator], Tracks] | None = None
                     ) -> tuple[Tracks, Landmarks, QueryFeatures]:
    """`scene`, with the tracks its landmarks were built from (`more` adds to them first)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([4, 4], [CAM.width - 4, CAM.height - 4], (N_POINTS, 2))
    xyz = backproject(uv, R_TRUE, T_TRUE)
    desc = unit_descriptors(rng.random((N_POINTS, 128)) ** 4)
    tracks = _tracks(xyz, desc, rng)
    if more is not None:
        tracks = more(tracks, rng)
    landmarks = build_landmarks(tracks, "synthetic", 120, LandmarksOptions(),
                                np.array([[CAM.width, CAM.height]] * len(MAPPING)))
    noisy = unit_descriptors(desc + 0.02 * rng.random(desc.shape))
    distract = unit_descriptors(rng.random((N_POINTS, 128)) ** 4)
    feats = QueryFeatures(np.concatenate([uv + rng.normal(0, 0.3, uv.shape),
                                          rng.uniform([0, 0], [CAM.width, CAM.height], (N_POINTS, 2))]),
                          np.concatenate([noisy, distract]).astype(np.float32))
    return tracks, landmarks, feats


def _map(tmp_path: Path, landmarks: Landmarks, monkeypatch: pytest.MonkeyPatch, feats: QueryFeatures,
         learned: tuple[np.ndarray, np.ndarray] | None = WRONG) -> Path:
    """A map whose scene coordinates put the photo at `learned` (None: coordinates that agree on
    no pose, as for a photo of another place), with the landmarks beside it."""
    coords = coordinate_map(learned, learned, noise=0.0) if learned is not None else \
        np.random.default_rng(5).normal(0.0, 2.0, (300, 3)) + [0.0, 0.0, 3.0]
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: coords.reshape(15, 20, 3))
    monkeypatch.setattr(sift_module, "extract_sift", lambda gray, n, ex: feats)
    path = make_map(tmp_path / "map.pt", landmarks.xyz[:10].astype(np.float32), META)
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    return path


def test_landmarks_keep_every_observation_and_read_back(tmp_path: Path):
    landmarks, _ = scene()
    obs = landmarks.observations
    assert obs is not None and len(obs.landmark) == int(landmarks.track_length.sum())
    assert np.all(np.diff(obs.image) >= 0) and [i for i, _, _ in obs.image_slices()] == list(range(len(MAPPING)))
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    back = read_landmarks(tmp_path / LANDMARKS_H5)
    assert back.observations is not None
    for name in ("landmark", "image", "uv", "descriptor", "image_K", "image_size"):
        assert np.array_equal(getattr(back.observations, name), getattr(obs, name)), name
    assert back.observations.image_names == obs.image_names


def test_observations_that_name_a_missing_landmark_are_refused():
    landmarks, _ = scene()
    obs = landmarks.observations
    obs.landmark[0] = len(landmarks)
    with pytest.raises(UsvcError, match="names a landmark outside"):
        Landmarks(landmarks.scene, landmarks.xyz, landmarks.descriptor, landmarks.view_dir, landmarks.view_angle_deg,
                  landmarks.track_length, 120, obs)


def test_verified_matches_lift_the_query_keypoints_to_their_points():
    landmarks, feats = scene()
    found = verified_matches(landmarks, feats, CAM, seed=0)
    assert found.images == len(MAPPING) and found.verified_pairs == len(MAPPING)
    assert len(found) >= 0.8 * N_POINTS * 2  # each point in several mapping images: one correspondence per image
    uv, _ = project_points(CAM, found.xyz, R_TRUE, T_TRUE)
    assert np.median(np.linalg.norm(uv - found.uv, axis=1)) < 1.0  # right correspondences
    assert np.all(found.keypoint < N_POINTS)  # no distractor was lifted
    _, other = scene(1)  # another place's keypoints: nothing survives matching and verification
    assert len(verified_matches(landmarks, other, CAM, seed=0)) < MIN_PAIR_INLIERS


def test_per_image_matches_are_the_same_bits_on_any_number_of_threads():
    """SIFT + PnP's pairs (verified by two-view geometry, or by a pose) matched and verified side by
    side on several threads give the matches of one thread, in the same order."""
    landmarks, feats = scene()
    every = np.arange(len(landmarks))
    runs = {"verified": lambda n: verified_matches(landmarks, feats, CAM, seed=3, threads=n),
            "pose-checked": lambda n: pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every, 2.0,
                                                           threads=n)}
    for kind, run in runs.items():
        one = run(1)
        assert one.verified_pairs == len(MAPPING) > 1, kind  # several pairs: the threads have work to share
        for threads in (2, 3, 8):
            many = run(threads)
            assert (many.images, many.matched_pairs, many.verified_pairs) == \
                (one.images, one.matched_pairs, one.verified_pairs), (kind, threads)
            for name in ("uv", "xyz", "landmark", "keypoint"):
                assert np.array_equal(getattr(many, name), getattr(one, name)), (kind, threads, name)


def test_a_wrong_learned_pose_still_localizes_through_the_fallback(tmp_path: Path, monkeypatch):
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats)
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    assert errors(est.initial_R, est.initial_t)[0] > 30  # the learned pose is the wrong one
    assert est.success and est.refine_path in ("global", "verified"), est.rejected
    rot, trans = errors(est.R, est.t)
    assert rot < 0.2 and trans < 0.01  # from 35 deg and a metre off
    rec = est.to_json()["refinement"]
    assert [h["path"] for h in rec["hypotheses"]] == ["guided", "global", "verified"]
    assert rec["hypotheses"][0]["inliers"] == 0 and rec["path"] == est.refine_path
    assert rec["verified_matching"]["verified_pairs"] == len(MAPPING)


def test_the_fallback_serves_a_photo_even_when_single_descriptors_fail(tmp_path: Path, monkeypatch):
    """The landmarks' one descriptor per point says nothing (all alike): matching against every
    landmark fails, SIFT + PnP's per-observation evidence does not."""
    landmarks, feats = scene()
    blank = Landmarks(landmarks.scene, landmarks.xyz, np.full_like(landmarks.descriptor, 11), landmarks.view_dir,
                      landmarks.view_angle_deg, landmarks.track_length, 120, landmarks.observations)
    path = _map(tmp_path, blank, monkeypatch, feats)
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    assert est.success and est.refine_path == "verified", est.rejected
    assert errors(est.R, est.t)[0] < 0.2


def test_prior_none_uses_the_fallback_alone(tmp_path: Path, monkeypatch):
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE))
    est = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior="none")).localize(photo(), CAM)
    assert est.success and est.refine_path == "verified"
    assert np.isnan(est.initial_R).all()  # no learned pose was solved for
    assert [h["path"] for h in est.to_json()["refinement"]["hypotheses"]] == ["verified"]
    assert est.to_json()["refinement"]["prior"] == "none"
    assert errors(est.R, est.t)[0] < 0.2
    # without intrinsics: the focal length from the verified matches (P4Pf)
    free = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior="none")).localize(photo(), None)
    assert free.success and abs(free.camera.params[0] / CAM.focal[0] - 1.0) < 0.05


def test_a_photo_of_another_place_is_still_refused(tmp_path: Path, monkeypatch):
    landmarks, _ = scene(0)
    _, other = scene(1)
    for prior in ("learned", "none"):
        path = _map(tmp_path, landmarks, monkeypatch, other, learned=None)
        est = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior=prior)).localize(photo(), CAM)
        assert not est.success and est.rejected and np.isnan(est.R).all(), prior
        assert "evidence" in est.to_json()  # what was weighed is still reported


def test_no_check_on_the_learned_pose_refuses_before_the_features_run(tmp_path: Path, monkeypatch):
    """The map's coordinates imply another focal length than the given one (a map that fits its
    scene poorly looks like this): the features, which find the right pose, decide."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats)
    reloc = Relocalizer(path, tmp_path / "encoder.pt")
    calls: list[str] = []
    real_features, real_focal = FeaturePath.answer, Relocalizer._focal_disagreement
    monkeypatch.setattr(FeaturePath, "answer", lambda *a, **k: calls.append("features") or real_features(*a, **k))
    monkeypatch.setattr(Relocalizer, "_focal_disagreement",
                        lambda *a, **k: calls.append("map focal") or real_focal(*a, **k))
    real_stretch = relocalizer_module.stretch_verdict
    for module in (relocalizer_module, path_module):  # on the map's coordinates; on the features' P4Pf
        monkeypatch.setattr(module, "stretch_verdict", lambda *a, **k: calls.append("stretch") or real_stretch(*a, **k))
    for intrinsics in (CAM, None):
        calls.clear()
        est = reloc.localize(photo(), intrinsics)
        assert calls and calls[0] == "features", (intrinsics, calls)
        assert est.success and est.refine_path in ("global", "verified"), est.rejected
        # from 35 deg off; without intrinsics a square-pixel focal is estimated for this fx != fy camera
        assert errors(est.R, est.t)[0] < (0.2 if intrinsics is not None else 3.0)
    # the learned pose alone (no landmarks): its own checks judge it, once it was found
    plain = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(refine="none"))
    calls.clear()
    plain.localize(photo(), None)
    assert calls == ["stretch"]


def test_prior_none_needs_landmarks_with_observations(tmp_path: Path, monkeypatch):
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats)
    with pytest.raises(UsvcError, match="prior=none needs relocalize.refine=features"):
        Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior="none", refine="none"))
    old = Landmarks(landmarks.scene, landmarks.xyz, landmarks.descriptor, landmarks.view_dir,
                    landmarks.view_angle_deg, landmarks.track_length, 120)
    write_landmarks(tmp_path / LANDMARKS_H5, old)
    with pytest.raises(UsvcError, match="needs landmarks with their observations"):
        Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior="none"))
    assert RelocalizeOptions(prior="maybe").problems()[0].startswith("prior=")


def test_the_fallback_registers_with_the_baselines_threshold():
    from usvc.relocalize.features.passes import VERIFIED_MAX_ERROR_PX
    from usvc.sfm.posing import QUERY_MAX_ERROR_PX

    assert VERIFIED_MAX_ERROR_PX == QUERY_MAX_ERROR_PX


def test_without_intrinsics_a_feature_pose_needs_a_focal_length_with_evidence(tmp_path: Path, monkeypatch):
    """A photo without intrinsics whose features give no focal length (P4Pf finds none: a stretched
    photo looks like this) is answered only where the map reads it well enough to give one; a
    focal length from a map that barely agrees (7 % of the cells) is no ground for a pose."""
    from test_refinement import PIXELS

    landmarks, feats = scene()
    monkeypatch.setattr(evidence_module, "estimate_focal_pose", lambda *a, **k: None)  # every P4Pf of the features
    right = backproject(PIXELS, R_TRUE, T_TRUE)
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE))
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: right.reshape(15, 20, 3))
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), None)
    assert est.success and est.confidence > 0.9, est.rejected  # the map's focal length, read from every cell
    weak = np.random.default_rng(3).normal(0.0, 2.0, right.shape) + [0.0, 0.0, 3.0]
    keep = np.random.default_rng(4).choice(len(right), 21, replace=False)
    weak[keep] = right[keep]
    monkeypatch.setattr(Relocalizer, "scene_coordinates", lambda self, g: weak.reshape(15, 20, 3))
    est = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), None)
    assert not est.success and "no focal length to trust" in est.rejected, est.rejected
    assert "Give its intrinsics" in est.rejected and re.search(r"confidence 0\.0\d+ < min_confidence 0\.1", est.rejected)


@pytest.mark.parametrize("judges", [True, False])
def test_where_only_the_map_could_tell_the_focal_length_it_judges_if_it_can(tmp_path: Path, monkeypatch, judges: bool):
    """A shallow view (the features cannot tell the focal length) of a map that reads the photo:
    the map's verdict decides where the map tells its own photos' focal lengths; where it does not
    (`map_judges_focal` False, from its `focal_error`), the answer stands with a warning."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE))
    asked: list[bool] = []  # verified=... of each call: which evidence was asked for the focal length
    monkeypatch.setattr(FeaturePath, "focal_verdict", lambda *a, verified=False, **k: asked.append(verified)
                        or relocalizer_module.FOCAL_UNOBSERVABLE)
    monkeypatch.setattr(Relocalizer, "_focal_disagreement",
                        lambda *a, **k: "the image implies a focal length 2.00x the given one")
    reloc = Relocalizer(path, tmp_path / "encoder.pt")
    reloc.map_judges_focal = judges
    est = reloc.localize(photo(), CAM)
    if judges:
        assert not est.success and est.rejected.startswith("the image implies a focal length 2.00x")
        assert not any("not checked" in w for w in est.warnings)
    else:
        assert est.success and est.refine_path == "guided" and errors(est.R, est.t)[0] < 0.2
        assert any(w.startswith("the given focal length was not checked") and "does not tell its own" in w
                   for w in est.warnings)
        assert asked == [False]  # not SIFT + PnP's matches: in a shallow view they cannot tell either
        assert est.to_json().get("verified") is None


def test_the_maps_focal_estimate_is_found_only_where_its_verdict_is_asked_for(tmp_path: Path, monkeypatch):
    """Where the photo's features tell the focal length (a deep enough view), the map's P4Pf on its
    coordinates is never computed; where they cannot, it is, once, and the map's verdict decides."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE))
    calls: list[int] = []
    real = relocalizer_module.estimate_focal
    monkeypatch.setattr(relocalizer_module, "estimate_focal", lambda *a, **k: calls.append(len(a[0])) or real(*a, **k))
    monkeypatch.setattr(query_cores.torch, "get_num_threads", lambda: 2)  # side work on the worker
    reloc = Relocalizer(path, tmp_path / "encoder.pt")
    reloc.map_judges_focal = True
    (fx, fy), (cx, cy) = CAM.focal, CAM.principal_point
    right = reloc.localize(photo(), CAM)
    wrong = reloc.localize(photo(), (2 * fx, 2 * fy, cx, cy))
    assert right.success and right.refine_path == "guided" and not right.warnings, right.rejected
    assert not wrong.success and wrong.rejected.startswith("the matched features imply a focal length 0.5")
    assert calls == []
    monkeypatch.setattr(FeaturePath, "focal_verdict",
                        lambda *a, **k: relocalizer_module.FOCAL_UNOBSERVABLE)
    right = reloc.localize(photo(), CAM)
    assert right.success and len(calls) == 1, right.rejected


def test_pose_checked_matches_are_the_per_image_matches_the_pose_explains():
    """SIFT + PnP's per-image matches around a known pose: only images that see the given landmarks
    are compared, every kept match lies within the threshold of its landmark's projection, and a
    keypoint matched in several images counts once per image."""
    landmarks, feats = scene()
    every = np.arange(len(landmarks))
    found = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every, 2.0)
    assert found.images == len(MAPPING) and found.verified_pairs == len(MAPPING)
    uv, _ = project_points(CAM, found.xyz, R_TRUE, T_TRUE)
    assert np.all(np.linalg.norm(uv - found.uv, axis=1) <= 2.0)
    assert np.all(found.keypoint < N_POINTS) and len(found) >= 0.8 * N_POINTS * 2  # several images per point
    assert np.array_equal(found.landmark[found.keypoint == found.keypoint[0]],
                          np.full(int((found.keypoint == found.keypoint[0]).sum()), found.landmark[0]))
    # landmarks seen by no mapping image in numbers: nothing is compared
    assert pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every[:MIN_PAIR_INLIERS - 1], 2.0).images == 0
    # a pose 20 px off explains none of the right matches within 2 px
    far = T_TRUE + np.array([20.0 * T_TRUE[2] / CAM.focal[0], 0.0, 0.0])
    assert len(pose_checked_matches(landmarks, feats, CAM, R_TRUE, far, every, 2.0)) == 0


def test_pose_checked_matches_take_the_most_covisible_images_when_capped():
    """features_final_images: at most that many images are matched, those observing the most of the
    given landmarks, and each keeps exactly the matches the uncapped pass finds in it."""
    landmarks, feats = scene()
    obs = landmarks.observations
    seen = np.arange(len(landmarks))
    every = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0)
    capped = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0, max_images=len(MAPPING) - 1)
    assert every.images == len(MAPPING) and capped.images == len(MAPPING) - 1
    last = min(obs.image_slices(), key=lambda s: s[2] - s[1])[0]  # the image observing the fewest of them
    only_last = np.isin(np.arange(len(landmarks)), obs.landmark[obs.image != last], invert=True)
    assert 0 < len(capped) < len(every) and not only_last[capped.landmark].any()
    pairs = lambda found: sorted(zip(found.keypoint.tolist(), found.landmark.tolist()))  # noqa: E731
    rest = pairs(every)
    for pair in pairs(capped):  # each kept image's matches are the uncapped pass's
        rest.remove(pair)
    assert len(rest) == len(every) - len(capped)
    same = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0, max_images=len(MAPPING))
    assert same.images == every.images and np.array_equal(same.keypoint, every.keypoint)


def test_pose_checked_matches_take_images_while_their_comparisons_fit():
    """features_final_comparisons: the most covisible images are taken while the descriptor
    comparisons they need fit the bound (the first always), each keeping exactly the matches the
    unbounded pass finds in it; a bound they all fit in changes nothing."""
    landmarks, feats = scene()
    obs = landmarks.observations
    seen = np.arange(len(landmarks))
    every = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0)
    pairs = lambda found: sorted(zip(found.keypoint.tolist(), found.landmark.tolist()))  # noqa: E731
    taken = []
    for bound in [1] + [2**k for k in range(14, 24)] + [10**12]:
        found = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0, max_comparisons=bound)
        rest = pairs(every)
        for pair in pairs(found):  # each taken image's matches are the unbounded pass's
            rest.remove(pair)
        taken.append(found.images)
    assert taken[0] == 1 and taken[-1] == len(MAPPING) and taken == sorted(taken)  # more as the bound grows
    assert any(1 < n < len(MAPPING) for n in taken)
    one = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0, max_comparisons=1)
    most = max(obs.image_slices(), key=lambda s: s[2] - s[1])[0]  # the image observing the most of them
    assert set(one.landmark.tolist()) <= set(obs.landmark[obs.image == most].tolist()) and len(one) > 0
    same = pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, seen, 2.0, max_comparisons=10**12)
    assert np.array_equal(same.keypoint, every.keypoint) and np.array_equal(same.landmark, every.landmark)


def test_refinement_on_inliers_recovers_the_pose_and_fails_without_inliers():
    landmarks, feats = scene()
    xyz = landmarks.xyz
    uv, _ = project_points(CAM, xyz, R_TRUE, T_TRUE)
    rng = np.random.default_rng(2)
    noisy = np.concatenate([uv + rng.normal(0, 0.2, uv.shape), rng.uniform([0, 0], [CAM.width, CAM.height], (80, 2))])
    points = np.concatenate([xyz, xyz[:80]])
    R0 = Rotation.from_rotvec([0.0, 0.003, 0.0]).as_matrix() @ R_TRUE  # about 0.17 deg off
    res = refine_on_inliers(noisy, points, CAM, R0, T_TRUE + 0.002, 4.0)
    ransac = solve_pnp(noisy, points, CAM, 4.0, 0, 10, "pycolmap")  # the noise's own limit: ~0.06 deg here
    assert res.success and errors(res.R, res.t)[0] < errors(ransac.R, ransac.t)[0] + 0.005 < errors(R0, T_TRUE)[0] / 2
    assert res.inlier_mask[:len(xyz)].mean() > 0.95 and res.inlier_mask[len(xyz):].mean() < 0.2
    far = refine_on_inliers(noisy, points, CAM, R_TRUE, T_TRUE + np.array([1.0, 0.0, 0.0]), 4.0)
    assert not far.success and np.isnan(far.R).all()


@pytest.mark.parametrize("learned", ["right", "wrong"])
def test_features_final_images_ends_with_the_baselines_evidence(tmp_path: Path, monkeypatch, learned: str):
    """relocalize.features_final=images: the answer the guided or global path found gets one more
    pass with SIFT + PnP's per-image matches around it, and says so; the default does not run it;
    SIFT + PnP's own path (the fallback) is that evidence already."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats, learned=(R_TRUE, T_TRUE) if learned == "right" else WRONG)
    plain = Relocalizer(path, tmp_path / "encoder.pt").localize(photo(), CAM)
    final = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(features_final="images")).localize(photo(), CAM)
    kinds = [p["kind"] for p in final.to_json()["refinement"]["passes"]]
    assert "images" not in [p["kind"] for p in plain.to_json()["refinement"]["passes"]]
    assert final.success and final.refine_path == plain.refine_path, final.rejected
    if plain.refine_path == "verified":
        assert "images" not in kinds
    else:
        assert kinds[-1] == "images"
        record = final.to_json()["refinement"]["passes"][-1]
        assert record["verified_pairs"] == len(MAPPING) and record["inliers"] >= 0.8 * N_POINTS
    rot, trans = errors(final.R, final.t)
    assert rot < 0.2 and trans < 0.01
    assert RelocalizeOptions(features_final="ransac").problems()[0].startswith("features_final=")
