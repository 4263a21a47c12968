"""The query's SIFT keypoints matched to the map's landmarks by descriptor: within a radius of
each landmark's projection under a pose (`guided_matches`, a guided pass's matching), and against
every landmark's one descriptor, or those of the mapping photos retrieved for the query
(`global_matches`, mutual). Both compare the landmarks' bytes as COLMAP's integer dots
(`byte_products`), on the CPU by tiles where the pairs in reach are many (`tiled_matching`), on a
torch device where one is given (`device_matching`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from usvc.relocalize.features.byte_products import DOT_SCALE, MASKED, ByteRows, ProductBlocks, dots
from usvc.relocalize.features.device_matching import best_two_and_column_max, masked_row_best_two
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.features.tiled_matching import row_best_two_within, tiles_pay
from usvc.relocalize.query_cores import Job, products_on_own_threads

_CHUNK = 2048  # rows of a descriptor-distance block (memory ~ CHUNK x keypoints x 4 bytes)
_PAIRS = 65536  # (landmark, keypoint) pairs compared at a time in guided matching
_DENSE_SIMILARITY = 8_000_000  # up to this many landmark x keypoint entries (32 MB), one matrix product on a device
_DENSE_PAIR_SHARE = 16  # guided matching on a device: one product when the pairs in reach are >= 1/16 of its entries
# Guided matching on the CPU: a pair in reach compared on its own (kd-tree, gathers, segmented maxima)
# costs about as much as this many entries of a tile's product (`tiled_matching`); tiles where
# they compute fewer such costs (mini at 640 x 480: its first pass 44 -> 12 ms, second 15 -> 10 ms)
_TILE_PAIR_COST = 40.0


def _distance(sim: np.ndarray) -> np.ndarray:
    """Euclidean distance of (near-)unit descriptors from their dot product (inf for -inf)."""
    return np.where(np.isfinite(sim), np.sqrt(np.maximum(2.0 - 2.0 * sim, 0.0)), np.inf).astype(np.float32)


def _one_to_one(rows: np.ndarray, cols: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for every column, only its closest row (ties: the first)."""
    order = np.lexsort((dist, cols))
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = cols[order][1:] != cols[order][:-1]
    sel = np.sort(order[keep])
    return rows[sel], cols[sel]


def _ratio_test(s1: np.ndarray, s2: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(passes Lowe's ratio test, nearest distance) from the two largest similarities."""
    d1, d2 = _distance(s1), _distance(s2)
    return np.isfinite(d1) & (d1 < ratio * d2), d1


def guided_matches(lm_uv: np.ndarray, lm_desc: np.ndarray, feats: QueryFeatures, radius: float,
                   ratio: float, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows) matched within `radius` px of each landmark's projection:
    each landmark's nearest keypoint by descriptor among those within the radius (the first on
    ties), Lowe's ratio test against the second nearest there, one landmark per keypoint.

    On the CPU, where the pairs in reach are many (a wide radius), landmarks and keypoints are
    binned into tiles and each tile's landmarks compared with the keypoints around it
    (`tiled_matching`). Otherwise a kd-tree lists the pairs within the radius: where they are
    few, only the pairs' descriptors are compared, and a segmented maximum over each landmark's
    pairs finds its nearest two; with a torch `device` and many pairs, one landmarks x keypoints
    product there gives every similarity, the pairs outside the radius masked (`device_matching`)."""
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(lm_uv) == 0 or len(feats) == 0:
        return empty
    if device is None and tiles_pay(lm_uv, feats.uv, radius, _TILE_PAIR_COST):
        first, s1, s2 = row_best_two_within(lm_uv, lm_desc, feats.uv, feats.scaled, radius)
        ok, d1 = _ratio_test(s1, s2, ratio)
        rows = np.flatnonzero(ok)
        return _one_to_one(rows, first[rows], d1[rows])
    pairs = cKDTree(lm_uv).sparse_distance_matrix(cKDTree(feats.uv), radius, output_type="ndarray")
    if len(pairs) == 0:
        return empty
    lm, kp = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    cells = len(lm_uv) * len(feats)
    if device is not None and cells <= _DENSE_SIMILARITY and len(lm) * _DENSE_PAIR_SHARE >= cells:
        first, s1, s2 = masked_row_best_two(lm_desc, feats.scaled, lm, kp, device)
        ok, d1 = _ratio_test(s1, s2, ratio)  # a landmark with no keypoint in reach has s1 = -inf: fails
        rows = np.flatnonzero(ok)
        return _one_to_one(rows, first[rows], d1[rows])
    order = np.argsort(lm * len(feats) + kp)  # by landmark, then keypoint (unique keys): the same order every run
    lm, kp = lm[order], kp[order]
    starts = np.flatnonzero(np.r_[True, lm[1:] != lm[:-1]])
    rows_with, counts = lm[starts], np.diff(np.r_[starts, len(lm)])
    sim = np.empty(len(kp), np.float32)
    for a in range(0, len(kp), _PAIRS):  # bounded memory: _PAIRS x 128 floats per side
        b = min(a + _PAIRS, len(kp))
        sim[a:b] = np.einsum("ij,ij->i", lm_desc[lm[a:b]], feats.scaled[kp[a:b]])
    best = np.maximum.reduceat(sim, starts)
    # the first pair of each landmark that reaches its best similarity
    first = np.flatnonzero(sim == np.repeat(best, counts))
    first = first[np.concatenate([[True], lm[first][1:] != lm[first][:-1]])]
    sim[first] = -np.inf
    second = np.maximum.reduceat(sim, starts)  # -inf for a landmark with one candidate
    ok, d1 = _ratio_test(best, second, ratio)
    return _one_to_one(rows_with[ok], kp[first][ok], d1[ok])


def global_matches(lm_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                   lm_bytes: ByteRows | None = None, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`landmark_matches` against every landmark, or only against landmark `rows` (sorted: those the
    mapping photos retrieved for the query observe, `retrieval`), the landmark rows returned
    being rows of the whole table either way."""
    if rows is None:
        return landmark_matches(lm_desc, feats, ratio, device, lm_bytes)
    li, ki = landmark_matches(lm_desc[rows], feats, ratio, device, None if lm_bytes is None else lm_bytes.take(rows))
    return rows[li], ki


def landmark_matches(lm_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                     lm_bytes: ByteRows | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(landmark rows, keypoint rows): each keypoint's nearest landmark by descriptor, ratio test
    against the second nearest landmark, mutual (the keypoint is also the landmark's nearest: the
    first keypoint that reaches the landmark's largest similarity). `lm_desc`: the landmarks'
    bytes as `byte_products.scaled` rows, whose products are their integer dots / 512²; on the CPU
    those integers come from `byte_products.dots` on `lm_bytes`, the same bytes held for it (made
    from `lm_desc` when not given: a caller holds them once per map), as int8 products where the
    CPU has them. With a torch `device` the products of the scaled rows and their reductions run
    there (`device_matching`): the same similarities."""
    k = len(feats)
    if k == 0 or len(lm_desc) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if device is not None:
        best_s, best_i, lm_max = best_two_and_column_max(feats.scaled, lm_desc, device)
    else:
        if lm_bytes is None:
            lm_bytes = ByteRows.of(np.rint(np.asarray(lm_desc, np.float64) * 512.0).astype(np.uint8))
        best_s = np.full((k, 2), -np.inf, dtype=np.float32)  # each keypoint's two largest similarities so far
        best_i = np.zeros(k, dtype=np.int64)
        lm_max = np.empty(len(lm_desc), dtype=np.float32)  # each landmark's largest similarity to a keypoint
        query = ByteRows.of(feats.codes, lm_bytes.signed is not None)
        blocks = ProductBlocks(k * min(_CHUNK, len(lm_desc)))  # one block's products, reused: a fresh
        with products_on_own_threads():  # multi-MB array per block costs its page faults; int8: this thread alone
            for start in range(0, len(lm_desc), _CHUNK):
                stop = min(start + _CHUNK, len(lm_desc))
                sim = dots(query, lm_bytes.rows_between(start, stop), blocks)  # (K, chunk): exact integers
                lm_max[start:stop] = sim.max(axis=0).astype(np.float32) / np.float32(DOT_SCALE)
                first, s1, s2 = _row_best_two(sim)  # per keypoint along rows
                best_i = np.where(s1 > best_s[:, 0], first + start, best_i)
                cand = np.stack([best_s[:, 0], best_s[:, 1], s1, s2], axis=1)
                cand.sort(axis=1)
                best_s = cand[:, :1:-1]  # the two largest, largest first
    reach = np.flatnonzero(best_s[:, 0] == lm_max[best_i])  # keypoints that reach their landmark's largest ...
    _, once = np.unique(best_i[reach], return_index=True)  # ... the first of them per landmark: mutual
    ok, _ = _ratio_test(best_s[:, 0], best_s[:, 1], ratio)
    mutual = np.zeros(k, dtype=bool)
    mutual[reach[once]] = True
    cols = np.flatnonzero(ok & mutual)
    return best_i[cols], cols


def _row_best_two(sim: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of a block of integer dots of bytes (`byte_products.dots`): the column of the largest
    entry (the first on ties), the largest and the second largest as the scaled rows' similarities
    (float32, / 512²: exact; -inf where the row has no other). Overwrites each row's largest entry:
    reductions along rows only, the contiguous (fast) direction, and no copy."""
    rows = np.arange(len(sim))
    first = np.argmax(sim, axis=1)
    s1 = sim[rows, first]
    sim[rows, first] = MASKED  # below every dot of bytes
    s2 = sim.max(axis=1) if sim.shape[1] > 1 else np.full(len(sim), MASKED, sim.dtype)
    scale = np.float32(DOT_SCALE)
    return first, s1.astype(np.float32) / scale, np.where(s2 == MASKED, -np.inf, s2.astype(np.float32) / scale
                                                          ).astype(np.float32)


def global_match_job(landmark_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                     background: bool | None = None, landmark_bytes: ByteRows | None = None,
                     rows: np.ndarray | None = None) -> Job:
    """`global_matches` (the keypoints' matches to every landmark, or to landmark `rows`, products on
    `device`), as a `Job`."""
    return Job(global_matches, landmark_desc, feats, ratio, device, landmark_bytes, rows, background=background)
