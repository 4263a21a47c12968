"""Pairs of an unposed capture by retrieval (usvc.sfm.retrieval_pairs): by content, not file order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from usvc.sfm import retrieval_pairs as rp
from usvc.sfm.options import SfmOptions


def _capture(groups: int = 3, per_group: int = 5, seed: int = 0) -> tuple[list[str], list[np.ndarray], dict[str, int]]:
    """Images of `groups` places, shuffled in name order: each place's images draw SIFT-like
    descriptors from that place's own 60 prototypes, with noise."""
    rng = np.random.default_rng(seed)
    prototypes = [rng.random((60, 128)).astype(np.float32) ** 4 for _ in range(groups)]
    place = rng.permutation(np.repeat(np.arange(groups), per_group))
    names, descriptors = [], []
    for i, g in enumerate(place):
        picks = prototypes[g][rng.integers(0, 60, 300)] + 0.02 * rng.random((300, 128)).astype(np.float32)
        d = picks / picks.sum(1, keepdims=True)
        names.append(f"img{i:02d}.jpg")
        descriptors.append(np.sqrt(d).astype(np.float32))
    return names, descriptors, dict(zip(names, place.tolist()))


def test_pairs_join_images_of_the_same_place_whatever_their_order(monkeypatch):
    names, descriptors, place = _capture()
    monkeypatch.setattr(rp, "_descriptors", lambda db_path: (names, descriptors))
    pairs = rp.retrieval_pairs(Path("unused.db"), neighbors=4, overlap=0, words=16, seed=0)
    assert pairs and all(place[a] == place[b] for a, b in pairs)
    # every image is paired with every other image of its place (4 neighbours, 5 images a place)
    assert len(pairs) == 3 * 10
    assert all(names.index(a) < names.index(b) for a, b in pairs) and pairs == sorted(pairs)
    assert rp.retrieval_pairs(Path("unused.db"), neighbors=4, overlap=0, words=16, seed=0) == pairs  # same bits


def test_name_order_neighbours_are_added(monkeypatch):
    names, descriptors, _ = _capture()
    monkeypatch.setattr(rp, "_descriptors", lambda db_path: (names, descriptors))
    pairs = set(rp.retrieval_pairs(Path("unused.db"), neighbors=1, overlap=2, words=16, seed=0))
    for i in range(len(names) - 2):
        assert (names[i], names[i + 1]) in pairs and (names[i], names[i + 2]) in pairs


def test_vlad_is_unit_length_and_tells_places_apart():
    names, descriptors, place = _capture(groups=2, per_group=3)
    centres = rp.vocabulary(descriptors, 16, seed=0)
    codes = np.stack([rp.vlad(d, centres) for d in descriptors])
    np.testing.assert_allclose(np.linalg.norm(codes, axis=1), 1.0, rtol=1e-5)
    sim = codes @ codes.T
    same = np.array([[place[a] == place[b] for b in names] for a in names])
    off = ~np.eye(len(names), dtype=bool)
    assert sim[same & off].min() > sim[~same].max()


def test_one_image_has_no_pairs(monkeypatch):
    monkeypatch.setattr(rp, "_descriptors", lambda db_path: (["a.jpg"], [np.ones((5, 128), np.float32)]))
    assert rp.retrieval_pairs(Path("unused.db"), 5, 5, 8, 0) == []


def test_retrieval_is_a_matching_option_and_its_counts_must_be_positive():
    assert SfmOptions(matching="retrieval").problems() == []
    assert any("retrieval_neighbors" in p for p in SfmOptions(retrieval_neighbors=0).problems())


def test_unposed_matching_over_the_exhaustive_limit_is_by_retrieval(tmp_path, monkeypatch):
    """matching=auto without poses above exhaustive_max_images matches the retrieved pairs."""
    from usvc.sfm import reconstruction

    seen = {}
    monkeypatch.setattr(reconstruction, "retrieval_pairs", lambda *a: seen.setdefault("pairs", [("a", "b")]))
    monkeypatch.setattr(reconstruction, "match_pairs", lambda db, pairs, *a: seen.setdefault("matched", pairs))
    monkeypatch.setattr(reconstruction, "image_names", lambda db: [])
    frames = [object()] * 4
    mode = reconstruction.match(frames, tmp_path / "db", tmp_path, SfmOptions(exhaustive_max_images=3),
                                has_poses=False, threads=1)
    assert mode == "retrieval" and seen["matched"] == [("a", "b")]


def test_pairs_from_a_colmap_database(tmp_path):
    """The descriptors are read from COLMAP's database as SIFT's extraction writes them."""
    import pycolmap

    names, descriptors, place = _capture()
    db_path = tmp_path / "database.db"
    db = pycolmap.Database.open(db_path)
    try:
        cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=64, height=48, params=[50, 32, 24], camera_id=1)
        db.write_camera(cam, use_camera_id=True)
        for k, (name, d) in enumerate(zip(names, descriptors), start=1):
            db.write_image(pycolmap.Image(name=name, camera_id=1, image_id=k), use_image_id=True)
            sift = np.round(d * d * 512).clip(0, 255).astype(np.uint8)  # back to SIFT's integer form
            db.write_descriptors(k, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, sift))
    finally:
        db.close()
    pairs = rp.retrieval_pairs(db_path, neighbors=4, overlap=0, words=16, seed=0)
    assert len(pairs) == 30 and all(place[a] == place[b] for a, b in pairs)
