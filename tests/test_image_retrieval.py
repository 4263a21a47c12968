"""Retrieval of the mapping photos most like a query (`usvc.relocalize.features.retrieval`): the
landmarks' visual words, the query's matches to the landmarks of the retrieved photos only, and
SIFT + PnP's fallback on those photos only; a map with no more photos than asked for is searched
whole, as before."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_fallback import CAM, MAPPING, _map, errors, photo, scene

from usvc.core.artifact_names import LANDMARKS_H5
from usvc.core.errors import UsvcError
from usvc.landmarks.build import retrieval_words
from usvc.landmarks.landmark_table import Landmarks, image_descriptors, unit_descriptors
from usvc.landmarks.landmarks_file import read_landmarks, write_landmarks
from usvc.relocalize.features.byte_products import ByteRows, scaled
from usvc.relocalize.features.matching import global_matches
from usvc.relocalize.features.retrieval import ImageRetrieval
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.verified_matching import verified_matches
from usvc.relocalize.relocalizer import RelocalizeOptions, Relocalizer


def test_the_landmarks_carry_their_words_and_read_them_back(tmp_path: Path):
    landmarks, _ = scene()
    assert landmarks.words is not None and landmarks.words.shape == (32, 128) and landmarks.words.dtype == np.float32
    write_landmarks(tmp_path / LANDMARKS_H5, landmarks)
    assert np.array_equal(read_landmarks(tmp_path / LANDMARKS_H5).words, landmarks.words)
    write_landmarks(tmp_path / LANDMARKS_H5, replace(landmarks, words=None))  # as older files hold them
    assert read_landmarks(tmp_path / LANDMARKS_H5).words is None
    with pytest.raises(UsvcError, match="retrieval words of shape"):
        replace(landmarks, words=np.zeros((4, 64), np.float32))


def _places(per_place: int = 3, places: int = 4, seed: int = 0) -> tuple[Landmarks, list[np.ndarray]]:
    """`landmarks` whose mapping photos show `places` places (`per_place` photos each, in turn:
    photo m shows place m % places), each place's photos sharing its own descriptors; and each
    place's descriptors."""
    landmarks, _ = scene(seed)
    obs = landmarks.observations
    rng = np.random.default_rng(seed)
    own = [rng.random((64, 128)) ** 4 for _ in range(places)]
    assert obs.keypoints is None  # test_fallback's scene: the observations are the photos' descriptors
    descriptor = obs.descriptor.copy()
    names = [f"m{m}.png" for m in range(per_place * places)]
    image = np.arange(len(obs.landmark)) % len(names)  # the observations dealt out among the photos
    for m in range(len(names)):
        rows = np.flatnonzero(image == m)
        picks = own[m % places][rng.integers(0, 64, len(rows))] + 0.01 * rng.random((len(rows), 128))
        descriptor[rows] = np.clip(np.rint(unit_descriptors(picks) * 512), 0, 255).astype(np.uint8)
    order = np.argsort(image, kind="stable")
    obs = replace(obs, landmark=obs.landmark[order], image=image[order].astype(np.int32), uv=obs.uv[order],
                  descriptor=descriptor[order], image_names=names, image_K=np.stack([CAM.K] * len(names)),
                  image_size=np.array([[CAM.width, CAM.height]] * len(names), np.int32))
    with_obs = replace(landmarks, observations=obs)
    return replace(with_obs, words=retrieval_words(obs, 16)), own


def test_retrieval_finds_the_photos_of_the_querys_place_and_their_landmarks():
    landmarks, own = _places()
    retrieval = ImageRetrieval(landmarks)
    rng = np.random.default_rng(3)
    for place in range(len(own)):
        query = QueryFeatures(rng.uniform(0, 100, (200, 2)),
                              unit_descriptors(own[place][rng.integers(0, 64, 200)]).astype(np.float32))
        found = retrieval.retrieve(query, 3)
        assert found.images is not None and sorted(found.images % len(own)) == [place] * 3
        obs = landmarks.observations
        assert np.array_equal(found.landmarks, np.unique(obs.landmark[np.isin(obs.image, found.images)]))
        assert found.record() == {"images": 3, "landmarks": len(found.landmarks)}
    # as many photos as the map has, or none asked for, or no words: every photo, as before
    assert retrieval.retrieve(query, 12).images is None and retrieval.retrieve(query, 0).images is None
    assert ImageRetrieval(replace(landmarks, words=None)).retrieve(query, 3).images is None


def test_image_descriptors_are_each_photos_own_unit_rows():
    landmarks, _ = _places()
    obs = landmarks.observations
    rows = image_descriptors(obs)
    assert len(rows) == len(obs.image_names)
    for m, d in enumerate(rows):
        assert np.allclose(d, unit_descriptors(obs.descriptor[obs.image == m]))


def test_matches_to_some_landmarks_are_the_matches_to_their_table_named_in_the_whole_one():
    landmarks, feats = scene()
    desc, raw = scaled(landmarks.descriptor), ByteRows.of(landmarks.descriptor)
    whole = global_matches(desc, feats, 0.8, None, raw)
    every = global_matches(desc, feats, 0.8, None, raw, np.arange(len(landmarks)))
    assert all(np.array_equal(a, b) for a, b in zip(whole, every))
    rows = np.arange(0, len(landmarks), 2)
    li, ki = global_matches(desc, feats, 0.8, None, raw, rows)
    sub_li, sub_ki = global_matches(desc[rows], feats, 0.8, None, raw.take(rows))
    assert len(li) > 20 and np.array_equal(li, rows[sub_li]) and np.array_equal(ki, sub_ki)
    assert np.isin(li, rows).all()


def test_the_fallback_matches_only_the_retrieved_photos():
    landmarks, feats = scene()
    every = verified_matches(landmarks, feats, CAM, seed=0)
    some = verified_matches(landmarks, feats, CAM, seed=0, images=np.array([1, 3]))
    assert every.images == len(MAPPING) and some.images == 2 and 0 < len(some) < len(every)
    assert np.isin(some.landmark, landmarks.observations.landmark[np.isin(landmarks.observations.image, [1, 3])]).all()


@pytest.mark.parametrize("k", [2, 0])
def test_a_wrong_learned_pose_localizes_through_the_retrieved_photos(tmp_path: Path, monkeypatch, k: int):
    """The relocalizer's fallback on a map of five photos, retrieving two of them (or every one):
    the answer is found either way, and SIFT + PnP's matching went to as many photos."""
    landmarks, feats = scene()
    path = _map(tmp_path, landmarks, monkeypatch, feats)
    est = Relocalizer(path, tmp_path / "encoder.pt", RelocalizeOptions(features_retrieval_images=k)).localize(
        photo(), CAM)
    assert est.success and errors(est.R, est.t)[0] < 0.2, est.rejected
    rec = est.to_json()["refinement"]
    assert rec["verified_matching"]["images"] == (k or len(MAPPING))
    retrieved = len(np.unique(landmarks.observations.landmark[np.isin(landmarks.observations.image,
                                                                       rec_images(landmarks, feats, k))]))
    assert [p["candidates"] for p in rec["passes"] if p["kind"] == "global"][0] == retrieved


def rec_images(landmarks: Landmarks, feats: QueryFeatures, k: int) -> np.ndarray:
    """The photos retrieval gives the query (every one for k = 0)."""
    found = ImageRetrieval(landmarks).retrieve(feats, k)
    return np.arange(len(MAPPING)) if found.images is None else found.images
