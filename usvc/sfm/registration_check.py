"""Did SfM pose an unposed capture consistently? The symmetry ambiguity (doppelgangers).

An object that looks alike from two sides (a can whose label repeats under a half turn) lets
incremental SfM register a run of photos on the wrong side: each wrong registration is consistent
with the matches it was registered from (to the photos of the look-alike side), so the
reprojection error cannot show it. The matches it was *not* registered from can: the photos taken
next to it share many verified matches with it (the whole view overlaps, not only the repeated
texture), and the reconstructed poses put those matches tens of pixels off their epipolar lines.

So every verified pair is scored against the reconstructed poses (`pose_check.pair_checks`), and
the reconstruction is refused when a pair that is at least as strong as the typical agreeing pair
(its verified matches at least their median) lies CONTRADICTED_RATIO thresholds or more off. In a
right reconstruction of a symmetric object the pairs that disagree are the look-alike ones, which
share only the repeated texture and so fewer matches; bird and office, posed by SfM from their
photos, have no such pair (docs/bad_input.md has the figures). The literature calls this SfM
disambiguation (Zach et al. 2010, Heinly et al. 2014, Cai et al. 2023).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from usvc.core.errors import SfmError
from usvc.core.scene import Frame
from usvc.sfm.pose_check import PairCheck, pair_checks

log = logging.getLogger(__name__)

# A pair contradicts the reconstruction when its median epipolar distance is this many pair
# thresholds (8 px at 640 px) or more: 32 px at 640 px. Right poses leave pairs at about a pixel; bird's
# loosest photo's pairs reach 2 thresholds; a photo turned by half a turn leaves hundreds of pixels.
CONTRADICTED_RATIO = 4.0
SHOWN_PAIRS = 3


def contradicted_pairs(checks: list[PairCheck]) -> list[PairCheck]:
    """Pairs that contradict the poses and are at least as strong as the median agreeing pair,
    strongest first."""
    agreeing = [c.matches for c in checks if c.ratio <= 1.0]
    if not agreeing:
        return []
    strong = float(np.median(agreeing))
    found = [c for c in checks if c.ratio >= CONTRADICTED_RATIO and c.matches >= strong]
    return sorted(found, key=lambda c: (-c.matches, c.a, c.b))


def wrongly_posed(bad: list[PairCheck], names: list[str]) -> list[str]:
    """The photos that look registered on the wrong side. Photos are taken in the order of their
    names (a sequential capture): where two photos next in that order contradict each other, the
    capture breaks, and the runs between breaks alternate between the two sides; the side with fewer
    photos is named (SfM registered most of them right). Without such breaks (an unordered
    collection), every photo of a contradicting pair is named."""
    order = sorted(names)
    contradicted = {frozenset((c.a, c.b)) for c in bad}
    breaks = [k for k in range(len(order) - 1) if frozenset((order[k], order[k + 1])) in contradicted]
    if not breaks:
        return sorted({n for c in bad for n in (c.a, c.b)})
    side, sides = 0, ([], [])
    for k, name in enumerate(order):
        sides[side].append(name)
        if k in breaks:
            side = 1 - side
    return min(sides, key=len)


def registration_report(db_path: Path, frames: list[Frame]) -> dict:
    """What the check saw: pairs scored, those that disagree, the contradicting ones and the photos
    they point at (`wrongly_posed`)."""
    checks = pair_checks(db_path, frames)
    bad = contradicted_pairs(checks)
    photos = wrongly_posed(bad, [f.name for f in frames])
    return {"pairs": len(checks), "pairs_disagreeing": sum(c.ratio > 1.0 for c in checks),
            "median_agreeing_matches": float(np.median([c.matches for c in checks if c.ratio <= 1.0]))
            if any(c.ratio <= 1.0 for c in checks) else float("nan"),
            "contradicted_pairs": [[c.a, c.b, c.matches, round(c.median_px, 1)] for c in bad],
            "contradicted_photos": photos}


def check_registration(db_path: Path, frames: list[Frame], scene: str) -> dict:
    """Refuse (SfmError, one line naming the photos) a reconstruction that strong verified pairs
    contradict; return the report otherwise."""
    report = registration_report(db_path, frames)
    bad = report["contradicted_pairs"]
    if bad:
        shown = "; ".join(f"{a} and {b} ({n} verified matches, {px:g} px off the epipolar lines)"
                          for a, b, n, px in bad[:SHOWN_PAIRS])
        more = f" and {len(bad) - SHOWN_PAIRS} more pairs" if len(bad) > SHOWN_PAIRS else ""
        raise SfmError(
            f"scene {scene!r}: SfM posed the photos inconsistently: {len(bad)} strongly matching pair(s) contradict "
            f"their reconstructed poses ({shown}{more}): {', '.join(report['contradicted_photos'][:8])}"
            f"{' ...' if len(report['contradicted_photos']) > 8 else ''} look registered on the "
            "wrong side of something that looks alike from two sides (a symmetric object or a repeated pattern): "
            "give the capture's poses, or add photos that show what tells the sides apart")
    log.info("registration check: %d pairs, %d disagree, none contradicts the poses", report["pairs"],
             report["pairs_disagreeing"])
    return report
