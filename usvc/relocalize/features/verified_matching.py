"""The evidence SIFT + PnP uses, for a query the learned pose does not lead to: the query's SIFT
keypoints matched to each mapping image's keypoints, the matches of each pair verified by two-view
geometry, and the verified matches of keypoints that observe an SfM point lifted to it through the
tracks (landmarks.h5's keypoints and observations).

Matching follows COLMAP's SIFT matcher (nearest neighbour by the angle between descriptors, from the
exact integer dot of their uint8 encoding as COLMAP computes it (`byte_products`), at most
MAX_DISTANCE, Lowe's ratio MAX_RATIO against the second nearest): against every keypoint of a
mapping image, cross-checked as COLMAP cross-checks (the ratio test on both sides,
`cross_checked_matches`), where the landmarks carry every keypoint (format version 3); against its
observations, mutual, for older landmarks. Verification is COLMAP's own
(`pycolmap.estimate_two_view_geometry`: essential, fundamental or homography matrix, whichever
explains the pair, at least MIN_PAIR_INLIERS inliers; at most MAX_PAIR_TRIALS RANSAC trials), as
the sfm stage and `python -m benchmarks.accuracy baseline-sift` match and verify. A keypoint matched in several
mapping images gives one correspondence per image, as in the baseline. The correspondences do not
depend on the query's intrinsics beyond verification, so they also judge a given focal length (P4Pf).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from usvc.core.scene import Camera
from usvc.landmarks.landmark_table import LandmarkObservations, Landmarks
from usvc.relocalize.features.byte_products import MASKED, ByteRows, ProductBlocks, angles, dots
from usvc.relocalize.features.device_matching import mutual_reductions, two_way_reductions
from usvc.relocalize.features.sift import QueryFeatures
from usvc.relocalize.pnp import in_image, project_points
from usvc.relocalize.query_cores import products_on_own_threads

log = logging.getLogger(__name__)
Item = TypeVar("Item")
Out = TypeVar("Out")

MAX_RATIO = 0.8  # COLMAP's SiftMatchingOptions.max_ratio
MAX_DISTANCE = 0.7  # COLMAP's max_distance: the angle (rad) between unit descriptors
MIN_PAIR_INLIERS = 15  # COLMAP's TwoViewGeometryOptions.min_num_inliers
# RANSAC trials per pair (COLMAP's default: 10,000). A query matched against only the keypoints that
# carry points has a lower inlier ratio than a full pair, and pairs that do not overlap then run
# every trial: on office, 10,000 took 4.2 s for 56 pairs and 1,000 1.3 s, for 3,620 inliers
# instead of 3,638 (one query, one thread).
MAX_PAIR_TRIALS = 1000
_VALID = {pycolmap.TwoViewGeometryConfiguration.CALIBRATED, pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED,
          pycolmap.TwoViewGeometryConfiguration.PLANAR, pycolmap.TwoViewGeometryConfiguration.PANORAMIC,
          pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC}


@dataclass
class VerifiedMatches:
    """2D-3D correspondences from verified pairs, and what it took to find them."""

    uv: np.ndarray  # (C,2) query keypoints (pixels of the feature image)
    xyz: np.ndarray  # (C,3) the SfM points they were lifted to
    landmark: np.ndarray  # (C,) landmark rows
    keypoint: np.ndarray  # (C,) query keypoint rows
    images: int  # mapping images compared
    matched_pairs: int  # pairs with at least MIN_PAIR_INLIERS descriptor matches
    verified_pairs: int  # pairs whose matches two-view geometry verified
    seconds: float

    def __len__(self) -> int:
        return len(self.uv)

    def record(self) -> dict:
        return {"images": self.images, "matched_pairs": self.matched_pairs, "verified_pairs": self.verified_pairs,
                "correspondences": len(self)}


def mutual_ratio_matches(query: ByteRows, image: ByteRows, scratch: ProductBlocks | None = None,
                         device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(query rows, image rows) matched as COLMAP's CPU matcher matches two sets of descriptors in
    its uint8 encoding: nearest by angle (the exact integer dot of the bytes, `byte_products`),
    within MAX_DISTANCE, ratio test, mutual nearest. `scratch`: the thread's blocks to hold the
    products (`byte_products.ProductBlocks`: a fresh array per call costs its page faults, ~a third
    of the products' own time on mini's images). With a torch `device` the products (of the bytes as
    float32: exact) and their reductions run there (`device_matching.mutual_reductions`), the same
    rules and the same integers."""
    if len(query) == 0 or len(image) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if device is not None:
        first, s1, s2, reach = mutual_reductions(query.values, image.values, device)
        q = _ratio_passes(s1, s2)
        q = q[reach[first[q]] == q]  # the first row to reach its column's largest entry: mutual
        return q, first[q]
    sim = dots(query, image, scratch)  # (K, n), exact integers
    first, s1, s2 = _best_two(sim)  # `sim` left as it was, for the mutual check
    return _mutual(sim, _ratio_passes(s1, s2), first)


def cross_checked_matches(query: ByteRows, image: ByteRows, device: str | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(query rows, image rows) matched as COLMAP's CPU matcher cross-checks two sets of
    descriptors (`SiftMatchingOptions.cross_check`): the nearest neighbour by angle of each query
    row among the image's rows and of each image row among the query's, each within MAX_DISTANCE
    and passing the ratio test on its own side, kept where the two agree. SIFT + PnP matches a
    query to a mapping photo's every keypoint so; `mutual_ratio_matches` tests the ratio on the
    query's side alone. The products are the bytes' exact integer dots (`byte_products`), on a torch
    `device` where given (`device_matching.two_way_reductions`)."""
    if len(query) == 0 or len(image) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if device is not None:
        (first, s1, s2), (back, b1, b2) = two_way_reductions(query.values, image.values, device)
    else:
        sim = dots(query, image)
        (first, s1, s2), (back, b1, b2) = _best_two(sim), _best_two(np.ascontiguousarray(sim.T))
    q = _ratio_passes(s1, s2)
    nearest = np.full(len(image), -1, np.int64)
    ok = _ratio_passes(b1, b2)
    nearest[ok] = back[ok]
    q = q[nearest[first[q]] == q]
    return q, first[q]


def _best_two(sim: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's column of its largest entry (the first on ties), the largest and the second
    largest (MASKED for a single column); `sim` is masked in place meanwhile and restored."""
    rows = np.arange(len(sim))
    first = np.argmax(sim, axis=1)
    s1 = sim[rows, first]
    if sim.shape[1] > 1:
        sim[rows, first] = MASKED
        s2 = sim.max(axis=1)
        sim[rows, first] = s1
    else:
        s2 = np.full(len(sim), MASKED, sim.dtype)
    return first, s1, s2


def _ratio_passes(s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """The rows whose nearest column (dot s1; s2 the second, MASKED or -inf where there is none)
    is within MAX_DISTANCE and passes the ratio test, by angle as COLMAP's matcher measures it."""
    d1, d2 = angles(s1), angles(s2)
    return np.flatnonzero((d1 <= MAX_DISTANCE) & (d1 < MAX_RATIO * d2))


def _mutual(sim: np.ndarray, q: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows `q` whose column `first[q]` has its first largest entry in that row (np.argmax along
    columns' rule), and those columns. Reductions along rows only, the contiguous direction (a
    column-wise arg-maximum is ~7x slower in numpy on these blocks): the column maxima; then, with
    the candidate rows' own entries masked, the maxima again, which tell the columns that another
    row reaches too (a tie, rare: only those columns are searched for their first such row)."""
    if len(q) == 0:
        return q, first[q]
    column_max = sim.max(axis=0)
    cols = first[q]
    q = q[sim[q, cols] == column_max[cols]]  # the row reaches its column's largest entry ...
    cols = first[q]
    if len(q) == 0:
        return q, cols
    own = sim[q, cols]
    sim[q, cols] = MASKED
    others = sim.max(axis=0)[cols]  # ... and no other row does, or it is the first that does
    sim[q, cols] = own
    ties = (others == own) | (np.bincount(cols, minlength=sim.shape[1])[cols] > 1)  # or two candidates reach it
    if ties.any():
        tied = np.flatnonzero(ties)
        keep = np.ones(len(q), bool)
        keep[tied] = np.argmax(sim[:, cols[tied]] == column_max[cols[tied]], axis=0) == q[tied]
        q = q[keep]
    return q, first[q]


def _pycolmap_camera(K: np.ndarray, width: int, height: int) -> pycolmap.Camera:
    """A mapping image's camera for COLMAP's two-view geometry: calibrated (its focal length is a
    prior, as the sfm stage registers posed photos), so the pair is verified by an essential
    matrix where one explains it, as SIFT + PnP's database verifies it."""
    camera = pycolmap.Camera(model="PINHOLE", width=int(width), height=int(height),
                             params=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])
    camera.has_prior_focal_length = True
    return camera


def _per_image(landmarks: Landmarks, image_descriptors: list[ByteRows] | None
               ) -> tuple[LandmarkObservations, list[tuple[int, int, int]], list[ByteRows]]:
    """The landmarks' observations, their (image, start, end) slices and each image's descriptors."""
    obs = landmarks.observations
    if obs is None:
        raise ValueError("landmarks without observations (format version 1) cannot be matched image by image")
    descs = image_descriptors if image_descriptors is not None else observation_descriptors(obs)
    return obs, obs.image_slices(), descs


def verified_matches(landmarks: Landmarks, feats: QueryFeatures, camera: Camera, seed: int = 0,
                     image_descriptors: list[ByteRows] | None = None, threads: int = 1,
                     device: str | None = None, keypoint_descriptors: list[ByteRows] | None = None,
                     focal_known: bool = True, images: np.ndarray | None = None) -> VerifiedMatches:
    """The query's correspondences to the landmarks through every mapping image (see the module).
    `camera` is the query's (pixels of the feature image). With `focal_known` (given intrinsics)
    its focal length is a prior, as in SIFT + PnP's database: COLMAP verifies each pair by an
    essential matrix where one explains it (else the fundamental matrix or a homography); without,
    by the fundamental matrix or a homography (an assumed focal length then plays no part).
    Landmarks that carry every keypoint of the mapping images (`MappingKeypoints`, format
    version 3) are matched as SIFT + PnP matches:
    the query against each image's every keypoint, cross-checked as COLMAP cross-checks
    (`cross_checked_matches`), each pair verified on all its matches, and the inliers whose keypoint
    observes a landmark lifted; older landmarks, against each image's observations
    (`mutual_ratio_matches`). `image_descriptors` / `keypoint_descriptors` are the descriptors of
    each image's observations (`observation_descriptors`) / keypoints (`mapping_descriptors`),
    held once per map. Each image is matched and its pair verified as one task, the tasks on
    `threads` threads (numpy's products and COLMAP's RANSAC release Python's lock; each pair has
    its own seeded RANSAC, so the matches are the same bits whatever the count). With a torch
    `device` (a GPU) the descriptor products run there. `images` (rows of the mapping images, e.g.
    those retrieved for the query) limits the matching to them; None: every one."""
    t0 = time.perf_counter()
    obs, sites = _matching_sites(landmarks, image_descriptors, keypoint_descriptors)
    if images is not None:
        wanted = set(np.asarray(images, np.int64).tolist())
        sites = [site for site in sites if site[0] in wanted]
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = int(seed)
    options.ransac.max_num_trials = MAX_PAIR_TRIALS
    qcam = pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                           params=[*camera.focal, *camera.principal_point])
    qcam.has_prior_focal_length = bool(focal_known)
    query = ByteRows.of(feats.codes)
    cross = obs.keypoints is not None
    scratch = None if cross or device else ProductBlocks(max((len(site[1]) for site in sites), default=0) * len(feats))

    def match_and_verify(site: tuple[int, np.ndarray, np.ndarray, ByteRows]
                         ) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """The pair's inliers (query rows, their landmarks) and whether it verified; None: fewer
        than MIN_PAIR_INLIERS matches at all."""
        image, uv, landmark, desc = site
        qi, mi = cross_checked_matches(query, desc, device) if cross else \
            mutual_ratio_matches(query, desc, scratch, device)
        if len(qi) < MIN_PAIR_INLIERS:
            return None
        w, h = obs.image_size[image]
        geometry = pycolmap.estimate_two_view_geometry(
            qcam, feats.uv, _pycolmap_camera(obs.image_K[image], w, h), uv.astype(np.float64),
            np.stack([qi, mi], axis=1).astype(np.uint32), options)
        inl = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
        if geometry.config not in _VALID or len(inl) < MIN_PAIR_INLIERS:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), False
        lm = landmark[inl[:, 1]].astype(np.int64)
        lifted = lm >= 0  # a keypoint that observes no landmark verifies the pair, lifts to nothing
        return inl[lifted, 0], lm[lifted], True

    with products_on_own_threads():  # the int8 products' torch calls on this query's threads alone
        found = [f for f in _in_order(match_and_verify, sites, threads) if f is not None]
    verified = [f for f in found if f[2]]
    kp = np.concatenate([k for k, _, _ in verified]) if verified else np.zeros(0, np.int64)
    lm = np.concatenate([m for _, m, _ in verified]) if verified else np.zeros(0, np.int64)
    uv = feats.uv[kp].reshape(-1, 2)
    return VerifiedMatches(uv, landmarks.xyz[lm].reshape(-1, 3), lm, kp, len(sites), len(found), len(verified),
                           time.perf_counter() - t0)


def _matching_sites(landmarks: Landmarks, image_descriptors: list[ByteRows] | None,
                    keypoint_descriptors: list[ByteRows] | None
                    ) -> tuple[LandmarkObservations, list[tuple[int, np.ndarray, np.ndarray, ByteRows]]]:
    """The observations, and per mapping image what a query is matched against: (image row, its
    keypoints' pixels, the landmark each observes (-1: none), their descriptors); every keypoint of
    the image where the landmarks carry them, else its observations."""
    obs = landmarks.observations
    if obs is None:
        raise ValueError("landmarks without observations (format version 1) cannot be matched image by image")
    kp = obs.keypoints
    if kp is not None:
        descs = keypoint_descriptors if keypoint_descriptors is not None else mapping_descriptors(obs)
        return obs, [(image, kp.uv[a:b], kp.landmark[a:b], d) for (image, a, b), d in zip(kp.image_slices(), descs)]
    descs = image_descriptors if image_descriptors is not None else observation_descriptors(obs)
    return obs, [(image, obs.uv[a:b], obs.landmark[a:b], d) for (image, a, b), d in zip(obs.image_slices(), descs)]


def pose_checked_matches(landmarks: Landmarks, feats: QueryFeatures, camera: Camera, R: np.ndarray, t: np.ndarray,
                         seen: np.ndarray, max_error_px: float,
                         image_descriptors: list[ByteRows] | None = None, threads: int = 1,
                         device: str | None = None, max_images: int = 0,
                         max_comparisons: int = 0) -> VerifiedMatches:
    """SIFT + PnP's per-image matches around a pose the query already has (R, t): the query's
    keypoints matched as `verified_matches` matches them, but only to the mapping images that
    observe at least MIN_PAIR_INLIERS of the landmarks in `seen` (the rows the pose was found with)
    and only to their observations of landmarks in front of the camera and inside the photo; each
    pair's matches are verified by the pose instead of two-view geometry (the landmark projects
    within `max_error_px` of the keypoint), and a pair with fewer than MIN_PAIR_INLIERS such matches
    gives none. With `max_images` > 0 only that many of those images are matched: the ones that
    observe the most of `seen` (the first in image order on ties), so the pass's images do not
    grow with the photos that made the map. With `max_comparisons` > 0 the images are taken in that order
    while the descriptor comparisons of those taken (compared keypoints x compared observations, summed)
    stay within it, the first always: a dense capture's most covisible images all see the whole
    photo, and each compares more than a sparse capture's. A keypoint matched in several images counts once per image, as in SIFT + PnP. Only
    the keypoints within `max_error_px` of one of an image's landmarks under the pose are compared
    with that image's observations (about a third of them): the others could give no match the pose
    explains, and so take no part in the mutual test either. The images are matched on `threads`
    threads (numpy's products release Python's lock), in order; with a torch `device` (a GPU) the
    products run there."""
    t0 = time.perf_counter()
    obs, slices, descs = _per_image(landmarks, image_descriptors)
    uv_lm, depth = project_points(camera, landmarks.xyz, R, t)
    visible = in_image(camera, uv_lm, depth)
    in_seen = np.zeros(len(landmarks.xyz), bool)
    in_seen[np.asarray(seen, np.int64)] = True
    shared = np.add.reduceat(in_seen[obs.landmark], [a for _, a, _ in slices]).astype(np.int64) \
        if slices else np.zeros(0, np.int64)  # each image's observations of `seen` (slices are contiguous, none empty)
    rows = np.flatnonzero(shared >= MIN_PAIR_INLIERS)
    rows = rows[np.argsort(-shared[rows], kind="stable")]  # the most covisible first (image order on ties)
    if 0 < max_images < len(rows):
        rows = rows[:max_images]

    # (landmark, keypoint) pairs the pose puts within max_error_px of each other, found once: only
    # keypoints within reach of one of an image's landmarks can give a match the pose explains, so
    # the others are left out of that image's products (and so of its mutual test)
    shown = np.flatnonzero(visible)
    reach = cKDTree(uv_lm[shown]).sparse_distance_matrix(cKDTree(feats.uv), max_error_px, output_type="ndarray") \
        if len(shown) and len(feats) else np.zeros(0, [("i", np.intp), ("j", np.intp), ("v", np.float64)])
    reach_lm, reach_kp = shown[reach["i"]], reach["j"].astype(np.int64)

    def compared(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, ByteRows]:
        """Image i's landmark rows, its observations compared (visible ones), the keypoints compared
        (within reach of one of them) and its descriptors."""
        rows = obs.landmark[slices[i][1]:slices[i][2]]
        kept = np.flatnonzero(visible[rows])
        mine = np.zeros(len(landmarks.xyz), bool)
        mine[rows[kept]] = True
        near = np.zeros(len(feats), bool)
        near[reach_kp[mine[reach_lm]]] = True
        return rows, kept, np.flatnonzero(near), descs[i]

    chosen = [compared(i) for i in rows]
    if max_comparisons > 0:
        total = np.cumsum([len(near) * len(kept) for _, kept, near, _ in chosen])
        chosen = chosen[:max(1, int(np.searchsorted(total, max_comparisons, side="right")))]
    chosen = [chosen[k] for k in np.argsort(rows[:len(chosen)], kind="stable")]  # back in image order

    query = ByteRows.of(feats.codes)
    scratch = ProductBlocks(max((len(kept) for _, kept, _, _ in chosen), default=0) * len(feats))

    def match(image: tuple[np.ndarray, np.ndarray, np.ndarray, ByteRows]) -> tuple[np.ndarray, np.ndarray] | None:
        """The image's matches the pose explains (query rows, landmark rows); None: too few matches at all."""
        rows, kept, near, desc = image
        if len(kept) == 0:
            return None
        qi, mi = mutual_ratio_matches(query.take(near), desc if len(kept) == len(rows) else desc.take(kept),
                                      None if device else scratch, device)
        if len(qi) < MIN_PAIR_INLIERS:
            return None
        qi = near[qi]
        lm = rows[kept[mi]].astype(np.int64)
        ok = np.linalg.norm(uv_lm[lm] - feats.uv[qi], axis=1) <= max_error_px
        return qi[ok], lm[ok]

    with products_on_own_threads():
        found = _in_order(match, chosen, threads)
    pairs = [f for f in found if f is not None and len(f[0]) >= MIN_PAIR_INLIERS]
    kp = np.concatenate([q for q, _ in pairs]) if pairs else np.zeros(0, np.int64)
    lm = np.concatenate([m for _, m in pairs]) if pairs else np.zeros(0, np.int64)
    return VerifiedMatches(feats.uv[kp].reshape(-1, 2), landmarks.xyz[lm].reshape(-1, 3), lm, kp, len(chosen),
                           sum(f is not None for f in found), len(pairs), time.perf_counter() - t0)


def _in_order(fn: Callable[[Item], Out], items: list[Item], threads: int) -> list[Out]:
    """`fn(item)` for every item, in order, on up to `threads` threads (in place with one)."""
    if threads > 1 and len(items) > 1:
        with ThreadPoolExecutor(max_workers=min(int(threads), len(items)), thread_name_prefix="usvc-pairs") as pool:
            return list(pool.map(fn, items))
    return [fn(item) for item in items]


class HeldKeypointDescriptors:
    """A map's `mapping_descriptors`, made when first asked for (only SIFT + PnP's evidence reads
    them: bird's 88,410 keypoints hold 45 MB as float32) and then held; safe for a relocalizer's
    photos on several threads."""

    def __init__(self, obs: LandmarkObservations | None) -> None:
        self._obs, self._lock = obs, threading.Lock()
        self._held: list[ByteRows] | None = None

    def get(self) -> list[ByteRows] | None:
        if self._obs is None or self._obs.keypoints is None:
            return None
        with self._lock:
            if self._held is None:
                self._held = mapping_descriptors(self._obs)
            return self._held


def mapping_descriptors(obs: LandmarkObservations, int8: bool | None = None) -> list[ByteRows] | None:
    """Each image's every keypoint's descriptors (`MappingKeypoints`), held for the products, in
    `image_slices` order; None for landmarks without them."""
    kp = obs.keypoints
    return None if kp is None else [ByteRows.of(kp.descriptor[a:b], int8) for _, a, b in kp.image_slices()]


def observation_descriptors(obs: LandmarkObservations, int8: bool | None = None) -> list[ByteRows]:
    """Each image's observations' descriptors (COLMAP's uint8 encoding, as the landmarks carry
    them), held for the products (`ByteRows.of`), in `image_slices` order."""
    return [ByteRows.of(obs.descriptor[a:b], int8) for _, a, b in obs.image_slices()]
