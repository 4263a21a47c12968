"""A mapping photo whose given pose is wrong is named by the pose check (usvc.sfm.pose_check) when it
disagrees with all of its pairs (at least MIN_ALL_PAIRS), whatever its median pair: a swapped photo
can keep only a few pairs, each off by less than the 2 thresholds of the median rule (9 of 9 pairs
at a median of 1.82 thresholds, as reported for office's rows 0 and 11 swapped)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from usvc.sfm.pose_check import (
    MIN_ALL_PAIRS,
    PairCheck,
    photo_disagrees,
    pose_agreement,
    poses_disagree,
    warn_if_poses_disagree,
)


def ratios(bad: list[float], good: int = 0) -> list[float]:
    """A photo's pair medians in thresholds: `bad` (> 1) and `good` pairs well under the threshold."""
    return [*bad, *[0.05] * good]


@pytest.mark.parametrize("pairs, named", [
    (ratios([1.82] * 9), True),                  # every pair off, under 2 thresholds (a swap, pose-guided pairs)
    (ratios([1.1, 1.3, 1.9]), True),             # all of MIN_ALL_PAIRS pairs
    (ratios([1.5, 1.9]), False),                 # too few pairs to tell a photo from noise
    (ratios([1.82] * 8, good=1), False),         # one agreeing pair: the median rule alone, 1.82 < 2
    (ratios([1.4] * 15, good=8), False),         # bird's loosest right photo: most pairs off, median 1.4
    (ratios([2.5] * 15, good=8), True),          # the median rule, as before
    (ratios([], good=12), False),
])
def test_a_photo_disagreeing_with_all_its_pairs_is_named(pairs: list[float], named: bool) -> None:
    assert MIN_ALL_PAIRS == 3
    assert photo_disagrees(pairs) is named


def test_all_pairs_rule_in_pose_agreement(monkeypatch: pytest.MonkeyPatch, caplog) -> None:
    """pose_agreement names the photo whose 9 pairs all disagree at 1.82 thresholds (the figures of
    a swap reported on office), and no photo whose pairs mostly agree."""
    checks = [PairCheck("swapped.jpg", f"n{k}.jpg", 100, 1.82 * 8.0, 8.0) for k in range(9)]
    checks += [PairCheck(f"n{k}.jpg", f"n{(k + d) % 20}.jpg", 100, 0.3, 8.0) for k in range(20) for d in (1, 2)]
    monkeypatch.setattr("usvc.sfm.pose_check.pair_checks", lambda db, frames: checks)
    stats = pose_agreement(Path("unused.db"), [])
    assert stats["pairs_disagreeing"] == 9 and not poses_disagree(stats)  # too few for the whole-capture rule
    assert stats["suspect_images"] == {"swapped.jpg": [9, 9]}
    with caplog.at_level(logging.WARNING, logger="usvc"):
        assert warn_if_poses_disagree(stats)
    assert "swapped.jpg (9 of 9 pairs)" in caplog.text and "n0.jpg" not in caplog.text
