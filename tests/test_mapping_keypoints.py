"""Every keypoint of the mapping images in the landmarks (format version 3), and SIFT + PnP's
matching against them: the query cross-checked against each image's every keypoint as COLMAP's
matcher cross-checks (the ratio test on both sides), the pairs verified on all their matches, the
inliers that observe a landmark lifted to it. The synthetic scene of test_fallback, whose mapping
images now also hold keypoints that observe no point."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_fallback import CAM, MAPPING, N_POINTS, R_TRUE, T_TRUE, _map, errors, photo, scene_and_tracks

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.landmarks.build import build_landmarks
from usvc.landmarks.landmark_table import Landmarks, MappingKeypoints, encode_descriptors, unit_descriptors
from usvc.landmarks.landmarks_file import observation_keypoints, read_landmarks, write_landmarks
from usvc.landmarks.options import LandmarksOptions
from usvc.relocalize.features.byte_products import ByteRows
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import (
    HeldKeypointDescriptors,
    cross_checked_matches,
    mutual_ratio_matches,
    verified_matches,
)
from usvc.relocalize.pnp import project_points
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer
from usvc.sfm.tracks_file import Tracks, read_tracks, write_tracks

EXTRA = 60  # keypoints per mapping image that observe no point


def with_keypoints(tracks: Tracks, rng: np.random.Generator) -> Tracks:
    """`tracks` plus every keypoint of each image: its observations and EXTRA that observe nothing."""
    point = tracks.point_of_obs()
    image, uv, desc, of = [], [], [], []
    for m in range(len(tracks.image_names)):
        mine = np.flatnonzero(tracks.obs_image == m)
        image.append(np.full(len(mine) + EXTRA, m, np.int32))
        uv.append(np.concatenate([tracks.obs_uv[mine], rng.uniform(0, [CAM.width, CAM.height], (EXTRA, 2))]))
        desc.append(np.concatenate([tracks.obs_descriptor[mine],
                                    encode_descriptors(unit_descriptors(rng.random((EXTRA, 128)) ** 4))]))
        of.append(np.concatenate([point[mine], np.full(EXTRA, -1)]))
    return replace(tracks, kp_image=np.concatenate(image), kp_uv=np.concatenate(uv).astype(np.float32),
                   kp_descriptor=np.concatenate(desc), kp_point=np.concatenate(of).astype(np.int64))


def scene(seed: int = 0) -> tuple[Tracks, Landmarks, QueryFeatures]:
    """test_fallback's scene, its tracks carrying every keypoint of the mapping images."""
    return scene_and_tracks(seed, with_keypoints)


def colmap_cross_check(a: np.ndarray, b: np.ndarray) -> set[tuple[int, int]]:
    """COLMAP's cross-checked matching written out: angles in float64, each side's nearest within
    0.7 rad passing the 0.8 ratio test, kept where the two sides agree."""
    angle = np.arccos(np.clip(a.astype(np.float64) @ b.astype(np.float64).T / 512.0 ** 2, -1.0, 1.0))

    def one_way(d: np.ndarray) -> dict[int, int]:
        out = {}
        for i, row in enumerate(d):
            order = np.argsort(row, kind="stable")
            d1, d2 = row[order[0]], (row[order[1]] if len(row) > 1 else np.inf)
            if d1 <= 0.7 and d1 < 0.8 * d2:
                out[i] = int(order[0])
        return out

    forward, backward = one_way(angle), one_way(angle.T)
    return {(i, j) for i, j in forward.items() if backward.get(j) == i}


def test_cross_checked_matches_are_colmaps_rule_on_any_device():
    rng = np.random.default_rng(3)
    base = encode_descriptors(unit_descriptors(rng.random((80, 128)) ** 4))
    image = encode_descriptors(unit_descriptors(base.astype(np.float64) + 30 * rng.random((80, 128))))
    # a second query row almost the first's twin: from the image's side the ratio test fails
    query = np.concatenate([base, encode_descriptors(unit_descriptors(base[:10].astype(np.float64) + 0.5))])
    expected = colmap_cross_check(query, image)
    assert 40 < len(expected) < 80
    q, i = cross_checked_matches(ByteRows.of(query), ByteRows.of(image))
    assert set(zip(q.tolist(), i.tolist())) == expected
    qd, idd = cross_checked_matches(ByteRows.of(query), ByteRows.of(image), device="cpu")  # the torch path
    assert np.array_equal(qd, q) and np.array_equal(idd, i)
    mq, mi = mutual_ratio_matches(ByteRows.of(query), ByteRows.of(image))
    assert set(zip(mq.tolist(), mi.tolist())) > expected  # the query's side alone keeps the twins' matches


def test_tracks_and_landmarks_carry_every_keypoint_and_read_back(tmp_path: Path):
    tracks, landmarks, _ = scene()
    write_tracks(tmp_path / "tracks.h5", tracks)
    again = read_tracks(tmp_path / "tracks.h5")
    for name in ("kp_image", "kp_uv", "kp_descriptor", "kp_point"):
        assert np.array_equal(getattr(again, name), getattr(tracks, name)), name
    kp = landmarks.observations.keypoints
    assert kp is not None and len(kp.image) == len(tracks.kp_image) == len(tracks.obs_image) + EXTRA * len(MAPPING)
    assert int((kp.landmark >= 0).sum()) == len(landmarks.observations.landmark)
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    back = read_landmarks(tmp_path / LANDMARKS_H5).observations.keypoints
    for name in ("image", "uv", "descriptor", "landmark"):
        assert np.array_equal(getattr(back, name), getattr(kp, name)), name


def _observation_arrays(landmarks: Landmarks) -> dict[str, np.ndarray]:
    obs = landmarks.observations
    return {name: getattr(obs, name) for name in ("landmark", "image", "uv", "descriptor", "image_K", "image_size")}


def test_observations_are_stored_as_their_keypoints_rows_and_read_back_the_same(tmp_path: Path):
    import h5py

    _, landmarks, _ = scene()
    obs = landmarks.observations
    # a landmark seen twice in one image (COLMAP's merged tracks have such): paired by position too
    twice = replace(obs, landmark=obs.landmark.copy())
    first_two = np.flatnonzero(twice.image == twice.image[0])[:2]
    twice.landmark[first_two] = twice.landmark[first_two[0]]
    kp_rows = [np.flatnonzero((obs.keypoints.image == obs.image[i]) & np.all(obs.keypoints.uv == obs.uv[i], axis=1)
                              )[0] for i in first_two]
    kp_landmark = obs.keypoints.landmark.copy()
    kp_landmark[kp_rows] = twice.landmark[first_two[0]]
    twice = replace(twice, keypoints=replace(obs.keypoints, landmark=kp_landmark))
    for case in (landmarks, replace(landmarks, observations=twice)):
        rows = observation_keypoints(case.observations)
        assert rows is not None and len(np.unique(rows)) == len(rows)
        write_landmarks(tmp_path / LANDMARKS_H5, case)
        with h5py.File(tmp_path / LANDMARKS_H5) as h5:
            assert "obs/keypoint" in h5 and "obs/descriptor" not in h5 and "obs/uv" not in h5
        back = read_landmarks(tmp_path / LANDMARKS_H5)
        for name, want in _observation_arrays(case).items():
            got = getattr(back.observations, name)
            assert got.dtype == want.dtype and np.array_equal(got, want), name


def test_an_observation_that_is_no_keypoint_keeps_its_own_copy(tmp_path: Path):
    import h5py

    _, landmarks, _ = scene()
    obs = landmarks.observations
    moved = obs.uv.copy()
    moved[3] += 0.25  # no keypoint is there
    odd = replace(landmarks, observations=replace(obs, uv=moved))
    assert observation_keypoints(odd.observations) is None
    write_landmarks(tmp_path / LANDMARKS_H5, odd)
    with h5py.File(tmp_path / LANDMARKS_H5) as h5:
        assert "obs/keypoint" not in h5 and "obs/descriptor" in h5
    back = read_landmarks(tmp_path / LANDMARKS_H5)
    for name, want in _observation_arrays(odd).items():
        assert np.array_equal(getattr(back.observations, name), want), name


def test_observation_rows_outside_the_keypoints_are_refused(tmp_path: Path):
    import h5py

    _, landmarks, _ = scene()
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    with h5py.File(tmp_path / LANDMARKS_H5, "a") as h5:
        rows = h5["obs/keypoint"][()]
        rows[0] = len(landmarks.observations.keypoints.image)
        h5["obs/keypoint"][...] = rows
    with pytest.raises(UsvcError, match="obs/keypoint names a row outside"):
        read_landmarks(tmp_path / LANDMARKS_H5)


def test_a_point_left_out_of_the_landmarks_leaves_its_keypoints_observing_nothing():
    tracks, _, _ = scene()
    bad = tracks.error.copy()
    bad[:5] = 99.0  # over landmarks.max_error_px
    landmarks = build_landmarks(replace(tracks, error=bad), "synthetic", 120, LandmarksOptions(),
                                np.array([[CAM.width, CAM.height]] * len(MAPPING)))
    kp = landmarks.observations.keypoints
    left_out = np.isin(tracks.kp_point, np.arange(5))
    assert left_out.any() and np.all(kp.landmark[left_out] == -1)
    kept = tracks.kp_point >= 5
    assert np.array_equal(landmarks.xyz[kp.landmark[kept]], tracks.xyz[tracks.kp_point[kept]])


def test_landmarks_without_every_keypoint_still_read_and_match_their_observations(tmp_path: Path):
    _, landmarks, feats = scene()
    obs = replace(landmarks.observations, keypoints=None)  # as format version 2 held them
    older = replace(landmarks, observations=obs)
    write_landmarks(tmp_path / LANDMARKS_H5, older)
    back = read_landmarks(tmp_path / LANDMARKS_H5)
    assert back.observations is not None and back.observations.keypoints is None
    assert HeldKeypointDescriptors(back.observations).get() is None
    assert len(verified_matches(back, feats, CAM, seed=0)) > N_POINTS


def test_keypoints_that_name_a_missing_landmark_are_refused():
    _, landmarks, _ = scene()
    kp = landmarks.observations.keypoints
    broken = MappingKeypoints(kp.image, kp.uv, kp.descriptor, np.where(kp.landmark < 0, -2, kp.landmark))
    with pytest.raises(UsvcError, match="names a landmark outside"):
        replace(landmarks, observations=replace(landmarks.observations, keypoints=broken))


def test_sift_and_pnps_evidence_matches_every_keypoint_and_lifts_only_landmarks():
    _, landmarks, feats = scene()
    held = HeldKeypointDescriptors(landmarks.observations)
    found = verified_matches(landmarks, feats, CAM, seed=0, keypoint_descriptors=held.get())
    assert held.get() is held.get()  # made once per map
    assert found.images == len(MAPPING) and found.verified_pairs == len(MAPPING)
    assert len(found) >= 0.8 * N_POINTS * 2 and np.all(found.landmark >= 0)
    uv, _ = project_points(CAM, found.xyz, R_TRUE, T_TRUE)
    assert np.median(np.linalg.norm(uv - found.uv, axis=1)) < 1.0
    assert np.all(found.keypoint < N_POINTS)  # no query distractor was lifted
    same = verified_matches(landmarks, feats, CAM, seed=0, threads=3)  # descriptors made here, on three threads
    assert np.array_equal(same.keypoint, found.keypoint) and np.array_equal(same.landmark, found.landmark)


def test_a_mapping_keypoint_like_an_observation_spoils_its_match_as_it_does_sift_and_pnps():
    """A keypoint that observes no point but looks like an observation makes the ratio test fail
    for that observation: SIFT + PnP loses the match, and so does the fallback now."""
    tracks, landmarks, feats = scene()
    first = np.flatnonzero(tracks.kp_image == 0)
    observed = first[tracks.kp_point[first] >= 0][:40]
    twins = tracks.kp_descriptor.copy()
    twins[first[-40:]] = twins[observed]  # 40 of image 0's point-less keypoints copy 40 observations
    spoiled = build_landmarks(replace(tracks, kp_descriptor=twins), "synthetic", 120, LandmarksOptions(),
                              np.array([[CAM.width, CAM.height]] * len(MAPPING)))
    before = verified_matches(landmarks, feats, CAM, seed=0)
    after = verified_matches(spoiled, feats, CAM, seed=0)
    lost = tracks.kp_point[observed]  # every point is a landmark here: point rows are landmark rows

    def count(found) -> int:
        return int(np.isin(found.landmark, lost).sum())

    assert count(before) >= 4 * 30  # those points, seen in most of the five images
    assert count(after) <= count(before) - 30  # image 0's matches to them are gone (all but a few of 40)
    assert np.array_equal(np.setdiff1d(after.landmark, lost), np.setdiff1d(before.landmark, lost))


def test_every_keypoint_is_cross_checked_and_observations_are_not(monkeypatch):
    from usvc.relocalize.features import verified_matching

    _, landmarks, feats = scene()
    calls = []
    real = verified_matching.cross_checked_matches
    monkeypatch.setattr(verified_matching, "cross_checked_matches", lambda *a, **k: calls.append(1) or real(*a, **k))
    verified_matches(landmarks, feats, CAM, seed=0)
    assert len(calls) == len(MAPPING)
    older = replace(landmarks, observations=replace(landmarks.observations, keypoints=None))
    verified_matches(older, feats, CAM, seed=0)
    assert len(calls) == len(MAPPING)  # observations: COLMAP's ratio test on the query's side, mutual


def test_prior_none_localizes_through_every_keypoint(tmp_path: Path, monkeypatch):
    _, landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats)
    est = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(prior="none")).localize(photo(), CAM)
    assert est.success and est.refine_path == "verified", est.rejected
    assert errors(est.R, est.t)[0] < 0.2
    assert est.to_json()["refinement"]["verified_matching"]["verified_pairs"] == len(MAPPING)
