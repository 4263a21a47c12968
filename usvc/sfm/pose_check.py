"""Do the given poses agree with the images' own geometry?

Before triangulating with fixed poses, every geometrically verified image pair is scored against
the fundamental matrix its given poses and intrinsics imply: the median Sampson distance (px) of
the pair's verified matches. Right poses leave image noise (about a pixel); poses attached to the
wrong photos (rows in another order, a shuffled list) leave tens to hundreds of pixels on the
pairs they touch, which triangulation alone hides by dropping the points that disagree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from usvc.core.scene import Frame

log = logging.getLogger(__name__)

# A pair whose matches sit further (median) from the poses' epipolar lines than this fraction of
# the images' long side disagrees (8 px at 640 px, 6 px at 480 px, 12 px at 960 px): epipolar
# errors, right or wrong, scale with the image. Measured medians over pairs: right poses 0.08 px
# (mini, 320 px), 0.25 px (office, 640 px), 2.1 px (bird, 960 px, whose pseudo ground truth is
# looser; 95 of 1771 pairs over 8 px); poses shuffled 30-50 px, office's rows in natural instead of
# lexicographic order 29 px, but LLFF rows shuffled on a 12-image 480 px capture only 6.8 px.
PAIR_MAX_MEDIAN_FRACTION = 8.0 / 640.0
# The poses do not belong to these images when the median pair disagrees, or when more than this
# fraction of the pairs does (a shuffle of nearby forward-facing views leaves the median pair under
# the threshold; two of 12 such views swapped disagree on about 20 % of the pairs, which passes).
MAX_DISAGREEING_PAIRS = 0.25
MIN_PAIR_MATCHES = 15
# One photo with a wrong pose (two rows swapped, one photo of another capture) spoils only its own
# pairs, too few for the rule above. A photo with at least MIN_IMAGE_PAIRS verified pairs is named
# when more than SUSPECT_IMAGE_PAIRS of them disagree and its median pair lies SUSPECT_IMAGE_MEDIAN
# thresholds or more off: on bird, whose pseudo ground truth is the loosest, one photo has 15 of its
# 23 pairs over the threshold but its median pair at 1.4 thresholds (17 px at 960 px); poses swapped
# between photos 0.6-1 m apart, 3-7 m from the scene, put their median pairs at 3.5-6 thresholds.
MIN_IMAGE_PAIRS = 3
SUSPECT_IMAGE_PAIRS = 0.5
SUSPECT_IMAGE_MEDIAN = 2.0
# A photo that disagrees with every one of its pairs, MIN_ALL_PAIRS or more, is named whatever its
# median: a swapped photo can keep only a few pairs (those that overlap its true view), each off by
# less than 2 thresholds. Right photos keep pairs that agree: on office the worst disagrees on 1 of
# its 25 pairs, on bird 15 of 23 (median 1.2 thresholds); none disagrees on all (each has 17+ pairs).
MIN_ALL_PAIRS = 3


def pair_threshold_px(a: Frame, b: Frame) -> float:
    """The epipolar disagreement threshold of a pair, in pixels of its larger image."""
    return PAIR_MAX_MEDIAN_FRACTION * max(a.camera.width, a.camera.height, b.camera.width, b.camera.height)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def _fundamental(a: Frame, b: Frame) -> np.ndarray:
    """F with x_b^T F x_a = 0 for pixel coordinates, from world-to-camera poses (x_c = R X + t)."""
    R = b.R @ a.R.T
    t = b.t - R @ a.t
    return np.linalg.inv(b.camera.K).T @ _skew(t) @ R @ np.linalg.inv(a.camera.K)


def sampson_px(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    Fa = ha @ F.T
    Fb = hb @ F
    num = np.einsum("ij,ij->i", hb, Fa) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


@dataclass(frozen=True)
class PairCheck:
    """One verified pair scored against poses: its photos, verified matches, the median Sampson
    distance (px) of those matches to the poses' epipolar lines, and the pair's threshold (px)."""

    a: str
    b: str
    matches: int
    median_px: float
    threshold_px: float

    @property
    def ratio(self) -> float:
        """Median distance in thresholds (> 1: the pair disagrees with the poses)."""
        return self.median_px / self.threshold_px


def pair_checks(db_path: Path, frames: list[Frame]) -> list[PairCheck]:
    """Every verified pair of posed frames with MIN_PAIR_MATCHES matches and a baseline, scored."""
    by_name = {f.name: f for f in frames}
    db = pycolmap.Database.open(db_path)
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        keypoints = {i: db.read_keypoints(i)[:, :2] for i in images}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    out = []
    for pair_id, geometry in zip(pair_ids, geometries):
        i, j = pycolmap.pair_id_to_image_pair(pair_id)
        matches = geometry.inlier_matches
        if len(matches) < MIN_PAIR_MATCHES or images.get(i) not in by_name or images.get(j) not in by_name:
            continue
        a, b = by_name[images[i]], by_name[images[j]]
        if np.linalg.norm(a.center - b.center) < 1e-9:
            continue  # no baseline: no epipolar geometry to check
        d = float(np.median(sampson_px(_fundamental(a, b), keypoints[i][matches[:, 0]], keypoints[j][matches[:, 1]])))
        out.append(PairCheck(a.name, b.name, len(matches), d, pair_threshold_px(a, b)))
    return out


def photo_disagrees(ratios: list[float]) -> bool:
    """Whether one photo's given pose is wrong, from its pairs' medians in thresholds (> 1: the pair
    disagrees): more than SUSPECT_IMAGE_PAIRS of its pairs disagree with its median pair
    SUSPECT_IMAGE_MEDIAN thresholds off, or all of them, MIN_ALL_PAIRS or more, disagree."""
    bad = sum(r > 1.0 for r in ratios)
    if len(ratios) < MIN_IMAGE_PAIRS:
        return False
    if bad == len(ratios) >= MIN_ALL_PAIRS:
        return True
    return bad > SUSPECT_IMAGE_PAIRS * len(ratios) and float(np.median(ratios)) >= SUSPECT_IMAGE_MEDIAN


def pose_agreement(db_path: Path, frames: list[Frame]) -> dict:
    """Per verified pair, the median Sampson distance of its matches under the given poses."""
    checks = pair_checks(db_path, frames)
    medians = [c.median_px for c in checks]
    limits = [c.threshold_px for c in checks]
    per_image: dict[str, list[float]] = {}  # each pair's median / threshold (> 1: it disagrees)
    for c in checks:
        for name in (c.a, c.b):
            per_image.setdefault(name, []).append(c.ratio)
    if not medians:
        return {"pairs": 0, "pairs_disagreeing": 0, "median_pair_epipolar_px": float("nan"),
                "pair_threshold_px": float("nan"), "worst_images": [], "suspect_images": {}}
    bad = [m > lim for m, lim in zip(medians, limits)]
    worst = sorted(per_image, key=lambda n: -float(np.median(per_image[n])))[:3]
    suspect = {name: [int(sum(r > 1.0 for r in ratios)), len(ratios)] for name, ratios in sorted(per_image.items())
               if photo_disagrees(ratios)}
    return {"pairs": len(medians), "pairs_disagreeing": int(sum(bad)),
            "median_pair_epipolar_px": float(np.median(medians)),
            "pair_threshold_px": float(np.median(limits)),
            "worst_images": worst if any(bad) else [],
            "suspect_images": suspect}  # name -> [its pairs that disagree, its pairs]


def poses_disagree(stats: dict) -> bool:
    """Whether the median pair, or more than MAX_DISAGREEING_PAIRS of the pairs, disagree."""
    if not stats["pairs"]:
        return False
    return (stats["median_pair_epipolar_px"] > stats["pair_threshold_px"]
            or stats["pairs_disagreeing"] > MAX_DISAGREEING_PAIRS * stats["pairs"])


def warn_if_poses_disagree(stats: dict) -> bool:
    """Log one warning (and return True) when the given poses disagree with the images' matches, or
    when some photos' poses do (naming them)."""
    if not poses_disagree(stats):
        suspect = stats.get("suspect_images") or {}
        if not suspect:
            return False
        named = ", ".join(f"{name} ({bad} of {n} pairs)" for name, (bad, n) in suspect.items())
        log.warning("the given poses of %d photo%s disagree with their matches, while the other photos' agree: %s "
                    "lie more than %.1f px from the poses' epipolar lines on most or all of their matched pairs: "
                    "are their poses swapped, or of other photos?", len(suspect), "s" * (len(suspect) > 1), named,
                    stats["pair_threshold_px"])
        return True
    log.warning("the given poses disagree with the images: on %d of %d matched image pairs the matches lie more "
                "than %.1f px (%.2f%% of the image size) from the poses' epipolar lines (median pair %.1f px; worst "
                "images %s): are the poses in another order than the images, or of other photos?",
                stats["pairs_disagreeing"], stats["pairs"], stats["pair_threshold_px"],
                100 * PAIR_MAX_MEDIAN_FRACTION, stats["median_pair_epipolar_px"], ", ".join(stats["worst_images"]))
    return True
