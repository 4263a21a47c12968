"""The per-image matching's arithmetic (`usvc/relocalize/features/byte_products.py`): exact integer dots of
COLMAP's uint8 descriptors on int8 units or as float32 products, and COLMAP's matcher rules on them
(`verified_matching.mutual_ratio_matches`)."""

from __future__ import annotations

import numpy as np
import pytest
from test_fallback import CAM, N_POINTS, R_TRUE, T_TRUE, scene

from usvc.landmarks.landmark_table import encode_descriptors, unit_descriptors
from usvc.relocalize.features import byte_products
from usvc.relocalize.features.byte_products import ByteRows, dots, int8_products
from usvc.relocalize.features.verified_matching import (
    MAX_DISTANCE,
    MAX_RATIO,
    mutual_ratio_matches,
    pose_checked_matches,
    verified_matches,
)


def test_mutual_ratio_matching_keeps_only_clear_mutual_nearest_neighbours():
    rng = np.random.default_rng(0)
    image = unit_descriptors(rng.random((50, 128)) ** 4)
    # rows 30 and 31: two keypoints nearest to the same image descriptor; only the closer one is mutual
    query = unit_descriptors(np.concatenate([image[:30] + 0.02 * rng.random((30, 128)),
                                             image[30:31] + 0.05 * rng.random((1, 128)),
                                             image[30:31] + 0.01 * rng.random((1, 128))]))
    q, m = mutual_ratio_matches(ByteRows.of(encode_descriptors(query)), ByteRows.of(encode_descriptors(image)))
    assert np.array_equal(q, [*range(30), 31]) and np.array_equal(m, [*range(30), 30])
    twins = ByteRows.of(encode_descriptors(np.stack([image[0], image[0]])))  # a twin: fails the ratio test
    assert len(mutual_ratio_matches(ByteRows.of(encode_descriptors(query[:1])), twins)[0]) == 0


PRODUCTS = [pytest.param(False, id="float32"), pytest.param(True, id="int8", marks=pytest.mark.skipif(
    not int8_products(), reason="no int8 products on this CPU (VNNI/AMX) or in this torch"))]


@pytest.mark.parametrize("int8", PRODUCTS)
@pytest.mark.parametrize("device", [None, "cpu"])  # numpy's products; torch's (a GPU's path) forced onto the CPU
def test_mutual_ratio_matching_is_colmaps_rule_on_the_bytes_with_ties(device, int8, monkeypatch):
    """COLMAP's matcher on its uint8 descriptors: nearest by the angle of dot / 512² (exact
    integers), ratio and distance tests, and the mutual test by column maxima gives np.argmax's
    answer (the first row of a column's largest entry), also where several rows reach it:
    duplicated keypoints tie exactly. Integer products on int8 units and float32 products give the
    same matches."""
    monkeypatch.setattr(byte_products, "INT8_MIN_ENTRIES", 0)  # these small products on int8 units too
    rng = np.random.default_rng(1)
    for trial in range(20):
        unit = unit_descriptors(rng.random((40 + trial, 128)) ** 4)
        image = encode_descriptors(unit)
        query = encode_descriptors(unit_descriptors(np.concatenate([unit[:25] + 0.03 * rng.random((25, 128)),
                                                                    rng.random((15, 128)) ** 4])))
        query = np.concatenate([query, query[rng.integers(0, 25, 5)]])  # exact duplicates: ties in a column
        query = query[rng.permutation(len(query))]
        q, m = mutual_ratio_matches(ByteRows.of(query, int8), ByteRows.of(image, int8), device=device)
        dot = query.astype(np.int64) @ image.astype(np.int64).T
        first = np.argmax(dot, axis=1)
        s1 = dot[np.arange(len(query)), first]
        second = np.sort(dot, axis=1)[:, -2]
        d1, d2 = (np.arccos(np.minimum(v / 512.0 ** 2, 1.0)) for v in (s1, second))
        want = np.flatnonzero((d1 <= MAX_DISTANCE) & (d1 < MAX_RATIO * d2) & (np.argmax(dot, axis=0)[first]
                                                                               == np.arange(len(query))))
        assert len(want) > 10, trial
        assert np.array_equal(q, want) and np.array_equal(m, first[want]), trial


def test_mutual_test_is_numpys_first_row_of_each_column_maximum_with_every_kind_of_tie():
    """The mutual test keeps a candidate row exactly where np.argmax along its column names it: on
    small integer dots full of ties (rows whose own nearest column ties with another, rows that
    failed the ratio test reaching a column's maximum, candidates sharing a column), for both
    dtypes the products give."""
    from usvc.relocalize.features.verified_matching import _mutual
    rng = np.random.default_rng(5)
    for trial in range(300):
        shape = (int(rng.integers(1, 12)), int(rng.integers(1, 9)))
        for dtype in (np.int32, np.float32):
            sim = rng.integers(0, 4, shape).astype(dtype)
            first = np.argmax(sim, axis=1)
            q = np.flatnonzero(rng.random(shape[0]) < 0.7)  # the rows that passed the ratio test
            want = q[np.argmax(sim[:, first[q]], axis=0) == q] if len(q) else q
            before = sim.copy()
            got, cols = _mutual(sim, q, first)
            assert np.array_equal(got, want) and np.array_equal(cols, first[want]), (trial, dtype)
            assert np.array_equal(sim, before)  # the block is left as it was


@pytest.mark.parametrize("smallest", [0, byte_products.INT8_MIN_ENTRIES])  # every product on int8 units; the default
def test_byte_products_are_exact_on_either_unit(monkeypatch, smallest):
    """int8 products (offsets added back) and float32 products of the bytes are the integers an
    int64 product gives, for the largest bytes too; rows taken keep them, and so does a reused block."""
    monkeypatch.setattr(byte_products, "INT8_MIN_ENTRIES", smallest)
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, (37, 128), dtype=np.uint8)
    b = np.concatenate([rng.integers(0, 256, (29, 128), dtype=np.uint8), np.full((1, 128), 255, np.uint8)])
    want = a.astype(np.int64) @ b.astype(np.int64).T
    blocks = byte_products.ProductBlocks(16)  # smaller than the product: grown on first use
    for int8 in ([False, True] if int8_products() else [False]):
        rows_a, rows_b = ByteRows.of(a, int8), ByteRows.of(b, int8)
        for out in (None, blocks):
            assert np.array_equal(dots(rows_a, rows_b, out).astype(np.int64), want), (int8, out)
        pick = np.array([5, 0, 36])
        assert np.array_equal(dots(rows_a.take(pick), rows_b, blocks).astype(np.int64), want[pick]), int8
        assert np.array_equal(dots(rows_a, rows_b.rows_between(3, 30), blocks).astype(np.int64), want[:, 3:30]), int8
        pick_b = np.array([2, 29, 7, 11])
        assert np.array_equal(dots(rows_a.take(pick), rows_b.take(pick_b).rows_between(1, 3)).astype(np.int64),
                              want[pick][:, pick_b[1:3]]), int8
    # the rows guided matching and matching against every landmark compare: code / 512, whose float32
    # products are those integers / 512² in any order (numpy's BLAS, a single dot, a sum of the terms)
    sa, sb = byte_products.scaled(a), byte_products.scaled(b)
    for got in (sa @ sb.T, np.einsum("ij,kj->ik", sa, sb), np.stack([sb @ row for row in sa]),
                (sa[:, None, ::-1] * sb[None, :, ::-1]).sum(axis=2, dtype=np.float32)):
        assert got.dtype == np.float32 and np.array_equal(got.astype(np.float64) * byte_products.DOT_SCALE, want)
    if int8_products() and smallest == 0:
        assert dots(ByteRows.of(a, True), ByteRows.of(b, True)).dtype == np.int32  # the int8 units ran


@pytest.mark.skipif(not int8_products(), reason="no int8 products on this CPU (VNNI/AMX) or in this torch")
def test_per_image_matches_are_the_same_with_int8_and_float32_products(monkeypatch):
    """The CPU's int8 products and float32 products of the bytes (every other CPU's, and a GPU's
    arithmetic) give the same matches, verified or pose-checked."""
    monkeypatch.setattr(byte_products, "INT8_MIN_ENTRIES", 0)  # the scene's small products on int8 units too
    landmarks, feats = scene()
    every = np.arange(len(landmarks))
    runs = [lambda: verified_matches(landmarks, feats, CAM, seed=3, threads=2),
            lambda: pose_checked_matches(landmarks, feats, CAM, R_TRUE, T_TRUE, every, 2.0, threads=2)]
    on_int8 = [run() for run in runs]
    monkeypatch.setattr(byte_products, "int8_products", lambda: False)
    for run, want in zip(runs, on_int8):
        got = run()
        assert len(got) > N_POINTS
        for name in ("uv", "xyz", "landmark", "keypoint"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
