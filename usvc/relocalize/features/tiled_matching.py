"""Each landmark's two most similar keypoints within a radius of its projection, by tiles of the
image: landmarks and keypoints are binned into square tiles at least the radius wide, and the
landmarks of each tile are compared (one matrix product) with the keypoints of the tiles around
it, the pairs further than the radius masked. It computes what one landmarks x keypoints product
with the radius as a mask computes (`guided_matches`' definition), on a fraction of its entries:
about 9 x tile^2 / image area, with no list of the pairs in reach to build first.

The radius test is the kd-tree's (squared distances in float64, <= radius^2), and within a tile's
block the keypoints keep their order, so ties go to the first keypoint as in the full product."""

from __future__ import annotations

import numpy as np

MAX_TILES = 48  # tiles across the points' extent at the most: a tile costs ~10 numpy calls, an entry ~15 ns


def _tiling(lm_uv: np.ndarray, kp_uv: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The lower corner and the size of the box around both point sets, and the tiles' side: the
    radius, or wider where that would make more than MAX_TILES tiles."""
    lo = np.minimum(lm_uv.min(axis=0), kp_uv.min(axis=0))
    span = np.maximum(lm_uv.max(axis=0), kp_uv.max(axis=0)) - lo
    return lo, span, max(float(radius), float(np.sqrt(max(span[0] * span[1], 1e-12) / MAX_TILES)))


def tiles_pay(lm_uv: np.ndarray, kp_uv: np.ndarray, radius: float, pair_cost: float) -> bool:
    """Whether tiles beat listing the pairs in reach, where a listed pair costs `pair_cost` entries
    of a tile's block: the share of all entries that are pairs in reach (evenly spread points), times
    the cost, against the share of entries the tiles compute (about 9 x tile^2 / area)."""
    if len(lm_uv) == 0 or len(kp_uv) == 0:
        return False
    _, span, tile = _tiling(lm_uv, kp_uv, radius)
    area = max(float(span[0] * span[1]), 1e-12)
    reach = 2 * int(np.ceil(radius / tile)) + 1
    return min(1.0, np.pi * radius * radius / area) * pair_cost >= min(1.0, reach * reach * tile * tile / area)


def _blocks(lm_uv: np.ndarray, kp_uv: np.ndarray, radius: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(landmark rows, keypoint rows in increasing order) per tile that holds landmarks: the
    keypoints of the tiles within reach of it."""
    lo, span, tile = _tiling(lm_uv, kp_uv, radius)
    nx, ny = int(span[0] // tile) + 1, int(span[1] // tile) + 1
    reach = int(np.ceil(radius / tile))

    def cell(uv: np.ndarray) -> np.ndarray:
        c = np.minimum(((uv - lo) // tile).astype(np.int64), [nx - 1, ny - 1])
        return c[:, 1] * nx + c[:, 0]

    kcell = cell(kp_uv)
    korder = np.argsort(kcell, kind="stable")
    kstart = np.searchsorted(kcell[korder], np.arange(nx * ny + 1))
    lcell = cell(lm_uv)
    lorder = np.argsort(lcell, kind="stable")
    lsorted = lcell[lorder]
    cuts = np.flatnonzero(np.r_[True, lsorted[1:] != lsorted[:-1], True])
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        cx, cy = int(lsorted[a]) % nx, int(lsorted[a]) // nx
        x0, x1 = max(cx - reach, 0), min(cx + reach, nx - 1)
        # a row of tiles is one run of the keypoints sorted by tile
        runs = [korder[kstart[y * nx + x0]:kstart[y * nx + x1 + 1]]
                for y in range(max(cy - reach, 0), min(cy + reach, ny - 1) + 1)]
        cols = np.sort(np.concatenate(runs))
        if len(cols):
            out.append((lorder[a:b], cols))
    return out


def row_best_two_within(lm_uv: np.ndarray, lm_desc: np.ndarray, kp_uv: np.ndarray, kp_desc: np.ndarray,
                        radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per landmark (rows of `lm_uv`, descriptors `lm_desc`, `byte_products.scaled` rows): among the keypoints within
    `radius` px, the row of the most similar (the first on ties), its similarity and the second
    largest (-inf where there are fewer such keypoints; the row then 0)."""
    n = len(lm_uv)
    first = np.zeros(n, np.int64)
    s1 = np.full(n, -np.inf, np.float32)
    s2 = np.full(n, -np.inf, np.float32)
    if n == 0 or len(kp_uv) == 0:
        return first, s1, s2
    blocks = _blocks(lm_uv, kp_uv, radius)
    most = max((len(r) * len(c) for r, c in blocks), default=0)
    # scratch reused by every block: fresh multi-MB arrays per block cost more in page faults than the arithmetic
    sim_buf, du_buf, dv_buf, far_buf = (np.empty(most, np.float32), np.empty(most), np.empty(most),
                                        np.empty(most, bool))
    lu, lv = np.ascontiguousarray(lm_uv[:, 0], np.float64), np.ascontiguousarray(lm_uv[:, 1], np.float64)
    ku, kv = np.ascontiguousarray(kp_uv[:, 0], np.float64), np.ascontiguousarray(kp_uv[:, 1], np.float64)
    r2 = float(radius) * float(radius)
    for rows, cols in blocks:
        shape = (len(rows), len(cols))
        size = shape[0] * shape[1]
        sim, du, dv, far = (b[:size].reshape(shape) for b in (sim_buf, du_buf, dv_buf, far_buf))
        np.matmul(lm_desc[rows], kp_desc[cols].T, out=sim)
        np.subtract.outer(lu[rows], ku[cols], out=du)
        np.multiply(du, du, out=du)
        np.subtract.outer(lv[rows], kv[cols], out=dv)
        np.multiply(dv, dv, out=dv)
        np.add(du, dv, out=du)
        np.greater(du, r2, out=far)
        np.putmask(sim, far, -np.inf)
        j = np.argmax(sim, axis=1)
        at = np.arange(shape[0])
        s1[rows] = sim[at, j]
        first[rows] = cols[j]
        if shape[1] > 1:
            sim[at, j] = -np.inf
            s2[rows] = sim.max(axis=1)
    first[~np.isfinite(s1)] = 0
    return first, s1, s2
