"""The order and orientation of exhaustive pairs, and their cut into chunks (usvc.sfm.pair_matching)."""

from __future__ import annotations

import itertools

import pytest

from usvc.sfm.pair_matching import chunks, exhaustive_pairs


@pytest.mark.parametrize("n, block", [(1, 50), (7, 50), (7, 3), (10, 4), (60, 50), (161, 50)])
def test_exhaustive_pairs_hold_every_pair_once(n, block):
    names = [f"{i:03d}.png" for i in range(n)]
    pairs = exhaustive_pairs(names, block)
    assert len(pairs) == n * (n - 1) // 2
    assert {frozenset(p) for p in pairs} == {frozenset(p) for p in itertools.combinations(names, 2)}


def test_exhaustive_pairs_are_oriented_as_colmaps_blocks():
    """Within one block, pairs run forward in COLMAP's order; across blocks, (j, i) when j's place in
    its block is not after i's (what COLMAP's exhaustive matcher does; checked against it, bit for
    bit, in test_sfm.py)."""
    names = list("abcdefg")
    assert exhaustive_pairs(names, 50) == list(itertools.combinations(names, 2))
    pairs = exhaustive_pairs(names, 3)  # blocks abc, def, g
    assert pairs[:3] == [("a", "b"), ("a", "c"), ("b", "c")]
    assert ("d", "a") in pairs and ("a", "e") in pairs and ("e", "b") in pairs and ("g", "a") in pairs
    assert ("a", "d") not in pairs and ("g", "b") in pairs and ("c", "g") not in pairs


@pytest.mark.parametrize("count", [1, 2, 3, 7, 100])
def test_chunks_cut_the_pairs_in_order(count):
    pairs = [(str(i), str(i + 1)) for i in range(20)]
    parts = chunks(pairs, count)
    assert len(parts) == min(count, 20) and all(parts)
    assert [p for part in parts for p in part] == pairs
    assert max(map(len, parts)) - min(map(len, parts)) <= 1


def test_chunks_of_no_pairs():
    assert chunks([], 4) == [[]]
