"""Localize one photo against a trained map: dense scene coordinates -> RANSAC-PnP -> pose, then
refinement: by features (relocalize.refine=features: the query's SIFT keypoints matched to the
map's landmarks, guided by that pose, LO-RANSAC PnP; matching against every landmark when the
learned pose is missing or too far off) or keypoint-guided (paper §3.2.2, refine=keypoints).

This is the one implementation behind the relocalize stage, the Python API and `usvc localize`,
so benchmark numbers and real use cannot drift apart. Here are the dense core (the network, the
focal length from its coordinates, the dense PnP: the learned pose) and the verdicts that weigh
the evidence; refinement by features is `usvc.relocalize.features`, reached through its one entry
point, `FeaturePath` (features/path.py). `Relocalizer._localize` runs the steps on a `Query`:
`_photo` (checks, undistortion, the photo's SIFT started beside the network), `_coordinates` (the
network; the focal length), `_learned_pose` (the dense PnP), `_refine_by_keypoints` or
`_refine_by_features`, `_dense_verdict` where the learned pose is the answer; `Query.estimate`
(pose_estimate.py) makes the answer.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from usvc.core.absolute_pose import estimate_focal
from usvc.core.errors import UsvcError
from usvc.core.images import Photo, read_photo
from usvc.core.options import check
from usvc.core.precision import autocast
from usvc.core.scene import Camera
from usvc.core.sift_grey import colmap_grey
from usvc.core.undistort import undistort
from usvc.landmarks.landmark_table import Landmarks
from usvc.model.encoder import cell_centers
from usvc.model.map_file import read_map_header
from usvc.model.preprocess import normalise, resize_to_short_side
from usvc.relocalize.answer_checks import (  # noqa: F401 (re-exported)
    FAR_RADII, FOCAL_UNCHECKED, FOCAL_UNCHECKED_MAP, MAP_DOES_NOT_JUDGE, UNGUIDED_PATHS, far_camera_verdict,
    features_alone_verdict, map_extent, poses_agree, unsupported_focal)
from usvc.relocalize.camera_checks import (
    estimated_focal_problem,
    focal_reason,
    implausible_focal,
    intrinsics_warnings,
    stretch_verdict,
)
from usvc.relocalize.features.path import (
    FOCAL_UNOBSERVABLE,
    FeaturePath,
    FeatureResult,
    PhotoFeatures,
    QueryEvidence,
    query_sift,
)
from usvc.relocalize.keypoint_refinement import RefineOptions, refine_pose
from usvc.relocalize.map_loading import find_landmarks, load_network, map_views
from usvc.relocalize.network_batch import NetworkBatcher
from usvc.relocalize.options import REFERENCE_SHORT_SIDE, RelocalizeOptions
from usvc.relocalize.photo_batch import check_workers, in_order, query_threads, threads_per_query
from usvc.relocalize.photo_processes import RelocalizerArgs, in_processes
from usvc.relocalize.pnp import PnPResult, reprojection_inliers, solve_pnp
from usvc.relocalize.pose_estimate import FEATURE_PATHS, PoseEstimate, Query, nan_R, nan_t
from usvc.relocalize.query_cores import Job, for_network, query_split, runs_beside
from usvc.relocalize.query_input import Intrinsics, as_gray, blank, camera_from_intrinsics, check_device, check_size

log = logging.getLogger(__name__)

CAMERA_FOV = "crop"  # a distorted query is undistorted as prepare undistorts mapping images


def refine_options(options: RelocalizeOptions) -> RefineOptions:
    return RefineOptions(radius_px=options.refine_radius_px, max_iterations=options.refine_max_iterations,
                         delta=options.refine_delta, min_correspondences=options.refine_min_correspondences)


class Relocalizer:
    """A loaded map (head + its encoder), ready to localize photos of that scene."""

    def __init__(self, map_path: str | Path, encoder_weights: str | Path | None = None,
                 options: RelocalizeOptions | None = None, device: str = "auto", seed: int = 0,
                 landmarks: str | Path | None = None) -> None:
        """`landmarks`: the map's landmarks.h5 for refine=features; None finds it beside the map
        (`landmarks.h5` in the map's folder, else `../landmarks/landmarks.h5` as the pipeline writes it)."""
        if not isinstance(map_path, (str, Path)):
            raise UsvcError(f"map_path must be the path of a map.pt, got {type(map_path).__name__}")
        device = check_device(device)
        self.options = options or RelocalizeOptions()
        check(self.options, "relocalize")
        self.seed = seed  # RANSAC's seed
        header = read_map_header(map_path)
        network = load_network(map_path, header, encoder_weights, self.options.precision, device)
        self.regressor, self.metadata, self.device = network.regressor, network.metadata, device
        self.precision, self.memory_format = network.precision, network.memory_format
        self.sift = query_sift(self.options, device)  # the query's SIFT, and where it runs
        if "short_side" not in self.metadata:
            raise UsvcError(f"map file {map_path} has no metadata field 'short_side' (the image size its head "
                            "was trained at): not a map the train stage wrote")
        self.short_side = int(self.metadata["short_side"])  # checked on load: an integer in range
        self.map_path = Path(map_path)
        # what a worker process needs to make the same relocalizer (`localize_many(processes=True)`): the
        # precision as resolved here, since `auto` times the products (a process starting beside others could
        # find them otherwise)
        encoder_weights = network.encoder_weights
        self.batcher: NetworkBatcher | None = None  # photos of threads side by side through the network together
        self.args = RelocalizerArgs(self.map_path, None if encoder_weights is None else Path(encoder_weights),
                                    replace(self.options, precision=self.precision), device, seed,
                                    None if landmarks is None else Path(landmarks))
        views = map_views(map_path, header, self.metadata, self.options.focal_tolerance)
        self.focal_range, self.map_judges_focal = views.focal_range, views.judges_focal
        self.keypoints_xyz, self.median_depth = views.keypoints_xyz, views.median_depth
        self.refine_options = refine_options(self.options)
        self.refine = self.options.refine == "keypoints" and self.keypoints_xyz is not None
        if self.options.refine == "keypoints" and self.keypoints_xyz is None:
            log.warning("map %s has no 3D keypoints: keypoint-guided refinement is off", self.map_path)
        self.landmarks: Landmarks | None = None
        self.landmarks_path: Path | None = None
        self.features: FeaturePath | None = None  # refinement by features, where the map has landmarks
        self.prior = self.options.prior == "learned"  # prior=none: the learned pose guides nothing
        if not self.prior and self.options.refine != "features":
            raise UsvcError(f"relocalize.prior=none needs relocalize.refine=features (got {self.options.refine!r}): "
                            "without the learned pose only the photo's features can give a pose")
        found = find_landmarks(landmarks, self.map_path, self.metadata, self.keypoints_xyz, self.prior) \
            if self.options.refine == "features" else None
        if found is not None:  # refinement by features
            self.landmarks, self.landmarks_path = found
            self.features = FeaturePath(self.landmarks, self.options, self.device, self.seed)

    def localize_many(self, photos: Iterable[tuple[np.ndarray | str | Path | Photo, Intrinsics | None]],
                      workers: int = 1, processes: bool = False) -> Iterator[PoseEstimate]:
        """`localize` of each (image, intrinsics) pair, `workers` photos at a time, the answers in the
        photos' order (`usvc.relocalize.photo_batch`). With several workers each query gets torch's
        current thread count divided among them, and the answers are bit for bit those of the photos
        localized one after the other with that many threads; for a folder on a machine with many
        cores, or with the network on a GPU. `processes`: the workers are processes, each with this
        relocalizer's own copy (`usvc.relocalize.photo_processes`: they start in seconds, then share
        no interpreter lock); a script that uses them needs the `if __name__ == "__main__":` guard
        that Python's spawned processes ask of it."""
        workers = check_workers(workers)
        if processes and workers > 1:
            items = ((image, intrinsics, {}) for image, intrinsics in photos)
            yield from in_processes(Relocalizer, self.args, items, workers,
                                    threads_per_query(torch.get_num_threads(), workers))
            return
        if workers == 1:
            for image, intrinsics in photos:
                yield self.localize(image, intrinsics)
            return
        with query_threads(threads_per_query(torch.get_num_threads(), workers)):
            yield from in_order(lambda pair: self.localize(*pair), photos, workers)

    def _localize_reduced(self, photo: Photo, intrinsics: Intrinsics | None, intrinsics_source: str) -> PoseEstimate:
        """A photo decoded reduced (over MAX_DECODE_PIXELS): its intrinsics, given for the photo's own
        pixels, are scaled to the decoded ones, and the answer's camera back to the photo's."""
        (w, h), (dw, dh) = photo.size, photo.bgr.shape[1::-1]
        given = None if intrinsics is None else camera_from_intrinsics(intrinsics, w, h)
        found = self.localize(photo.bgr, None if given is None else given.scaled(dw, dh), channels="bgr",
                              intrinsics_source=intrinsics_source)
        if found.camera is not None:
            found.camera = given if given is not None else found.camera.scaled(w, h)
        note = (f"the photo is {w}x{h} = {w * h / 1e6:.0f} megapixels: localized from its pixels decoded at "
                f"1/{photo.reduction} ({dw}x{dh})")
        log.info("%s", note)
        found.warnings.append(note)
        return found

    def working_image(self, gray01: np.ndarray) -> tuple[np.ndarray, float]:
        """The image at the map's working short side, as its head was trained, and the resize factor."""
        if self.short_side and min(gray01.shape) != self.short_side:
            return resize_to_short_side(gray01, self.short_side)
        return gray01, 1.0

    def scene_coordinates(self, gray01: np.ndarray) -> np.ndarray:
        """(h, w, 3) world coordinates of the image's 8x8 cells, as float64."""
        if self.batcher is not None:
            return self.batcher(gray01)
        return self.scene_coordinates_of([gray01])[0]

    def batch_network(self, max_batch: int = 16, wait_s: float = 0.003) -> None:
        """From now on, photos that threads localize side by side go through the network together
        (`network_batch`: for a GPU; a batch's answers may differ from one photo's in the last bits)."""
        self.batcher = NetworkBatcher(self.scene_coordinates_of, max_batch, wait_s) if max_batch > 1 else None

    @torch.inference_mode()
    def scene_coordinates_of(self, grays: list[np.ndarray]) -> list[np.ndarray]:
        """scene_coordinates of photos of one size, through the network as one batch."""
        with autocast(self.precision, self.device), for_network():
            images = torch.cat([normalise(g) for g in grays]) if len(grays) > 1 else normalise(grays[0])
            out = self.regressor(images.to(self.device).contiguous(memory_format=self.memory_format)).float()
        return [o.permute(1, 2, 0).double().cpu().numpy() for o in out]

    def localize(self, image: np.ndarray | str | Path | Photo, intrinsics: Intrinsics | None, *,
                 channels: str = "rgb", intrinsics_source: str = "") -> PoseEstimate:
        """Pose of one photo. ``intrinsics=None`` estimates the focal length with the pose
        (principal point at the image centre, no distortion); a distorted Camera is undistorted
        first, exactly as the prepare stage undistorts mapping images.

        An array is uint8, HxW grey or HxWx3 in RGB order (``channels="rgb"``, as PIL and imageio
        give it) or BGR (``channels="bgr"``, as ``cv2.imread`` gives it); a path is read with its
        EXIF orientation applied (`usvc.core.images.read_photo`, whose `Photo` is also taken, so
        that a caller can decode the next photo while this one is localized). ``intrinsics_source`` names where the intrinsics came from (e.g.
        "the EXIF focal length (...)") in the reason a query they fail gives.

        Every failed answer says why in ``rejected``; doubts that did not stop it (a principal
        point far off the centre, non-square pixels) are in ``warnings``."""
        if self.features is not None and runs_beside():  # side work on the worker thread: the threads are
            with query_split(torch.get_num_threads()):  # split between the two sides (`query_cores`)
                return self._localize(image, intrinsics, channels=channels, intrinsics_source=intrinsics_source)
        return self._localize(image, intrinsics, channels=channels, intrinsics_source=intrinsics_source)

    def _localize(self, image: np.ndarray | str | Path | Photo, intrinsics: Intrinsics | None, *,
                  channels: str, intrinsics_source: str) -> PoseEstimate:
        if not isinstance(intrinsics_source, str):
            raise UsvcError(f"intrinsics_source must be a string, got {type(intrinsics_source).__name__}")
        if isinstance(image, (str, Path, Photo)):  # EXIF orientation applied, as for mapping images
            photo = image if isinstance(image, Photo) else read_photo(image)
            if photo.reduction > 1:
                return self._localize_reduced(photo, intrinsics, intrinsics_source)
            image, channels = photo.bgr, "bgr"
        q = self._photo(image, intrinsics, channels, intrinsics_source)
        if isinstance(q, PoseEstimate):  # nothing to localize: a blank photo, a focal length no camera has
            return q
        self._coordinates(q)
        if q.camera is None and self.features is None:  # no focal length, and no features to find one
            t3 = time.perf_counter()
            seconds = {"preprocess": q.t1 - q.t0, "network": q.t2 - q.t1, "pnp": t3 - q.t2, "refine": 0.0,
                       "total": t3 - q.t0}
            return PoseEstimate(False, nan_R(), nan_t(), 0, q.cells, seconds, focal_estimated=True,
                                rejected=q.no_focal, warnings=q.warnings, pose_found=False)
        self._learned_pose(q)
        # the photo's features, and (on the worker, while the guided passes run) their matches to every landmark
        found = self.features.gather(q.sift_job, q.intrinsics) \
            if self.features is not None and q.sift_job is not None else None
        # Evidence before verdicts: the learned pose is a hypothesis. No check on it refuses the photo
        # before the features have had their say; the checks below judge the final answer with the
        # evidence that produced it.
        if q.dense.success and self.refine:
            self._refine_by_keypoints(q)
        if found is not None:
            self._refine_by_features(q, found)
        if q.dense.success and q.path not in FEATURE_PATHS and not q.rejected:
            q.rejected = self._dense_verdict(q)
        return q.estimate(self._extent, self.options,
                          self.options.refine if (self.refine or self.features is not None) else "none")

    def _photo(self, image: np.ndarray, intrinsics: Intrinsics | None, channels: str,
               source: str) -> Query | PoseEstimate:
        """The photo as the steps take it: the network's grey (undistorted, at the map's working size)
        and its camera; the photo's SIFT started beside the network. A photo with nothing to localize
        (blank, or a focal length no camera has) is answered at once."""
        t0 = time.perf_counter()
        gray = as_gray(image, channels)  # the network's luma (checks the array too)
        # COLMAP's SIFT on the grey COLMAP's reader makes, as the sfm stage extracted the mapping photos
        # (`sift_grey`); OpenCV's on the luma, as `sfm.extractor=opencv` extracts them
        sift_gray = colmap_grey(np.asarray(image), rgb=channels == "rgb").astype(np.float32) / 255.0 \
            if self.features is not None and self.sift.kind == "colmap" else gray
        h, w = gray.shape
        check_size(w, h)
        given = None if intrinsics is None else camera_from_intrinsics(intrinsics, w, h)
        warnings = intrinsics_warnings(given) if given is not None else []
        for line in warnings:
            log.warning("%s", line)
        early = blank(gray)  # a reason to answer without looking: a blank photo, a focal length no camera has
        if not early and given is not None:
            focal = float(np.sqrt(given.focal[0] * given.focal[1]))
            early = implausible_focal(focal, w, h, source or f"the given focal length ({focal:.4g} px)")
        if early:
            hw = self.working_image(gray)[0].shape
            return PoseEstimate(False, nan_R(), nan_t(), 0, -(-hw[0] // 8) * -(-hw[1] // 8),
                                {"total": time.perf_counter() - t0}, camera=given, focal_estimated=intrinsics is None,
                                rejected=early, warnings=warnings, pose_found=False)
        camera = None
        if given is not None:
            if sift_gray is not gray:
                sift_gray = undistort(sift_gray, given, CAMERA_FOV, where="query image")[0]
            gray, camera = undistort(gray, given, CAMERA_FOV, where="query image")
        full_camera = camera  # undistorted, at the photo's size: what features see (in sift_gray)
        job = self.features.start(sift_gray, self.sift) if self.features is not None else None  # beside the network
        gray, resize = self.working_image(gray)
        if resize != 1.0 and camera is not None:
            camera = camera.scaled(gray.shape[1], gray.shape[0])
        return Query(t0, w, h, intrinsics is not None, source, given, warnings, gray, resize, camera, full_camera, job)

    def _coordinates(self, q: Query) -> None:
        """The network's scene coordinates of the photo's cells, and where the photo has no focal
        length, the one they imply (P4Pf) if the map reads the photo (else why not: `no_focal`)."""
        q.t1 = time.perf_counter()
        q.coords = self.scene_coordinates(q.gray)
        q.t2 = time.perf_counter()
        hc, wc = q.coords.shape[:2]
        q.cells = hc * wc
        # Scale the threshold with the working resolution: 10 px at 480 px is 5 px at 240 px.
        q.threshold = self.options.max_error_px * min(q.gray.shape) / REFERENCE_SHORT_SIDE
        q.pixels = cell_centers(hc, wc, "colmap").permute(1, 2, 0).reshape(-1, 2).double().numpy()
        if q.camera is not None or not self.prior:
            return
        camera = estimate_focal(q.pixels, q.coords.reshape(-1, 3), q.gray.shape[1], q.gray.shape[0], q.threshold,
                                self.seed)
        if camera is None:
            q.no_focal = ("no camera explains the map's scene coordinates of this photo, so its focal length "
                          "cannot be estimated: not a view of this map's scene (or too dark or blurred?)")
            return
        w, h, f = q.width, q.height, camera.params[0] / q.resize
        q.no_focal = estimated_focal_problem(f, w, h, self.focal_range)
        if q.no_focal:  # the map does not read this photo: its dense answer is no answer
            q.no_focal += ": the map does not recognise this photo (another place, or stretched or cropped?)"
            return
        q.camera = camera
        q.given = q.full_camera = Camera("SIMPLE_PINHOLE", w, h, (f, w / 2, h / 2))

    def _learned_pose(self, q: Query) -> None:
        """RANSAC-PnP on the map's coordinates (none without a focal length, or with prior=none:
        features may still find one); and the map's own focal estimate, for its verdicts, readied
        (computed in place only when asked for) where a given focal length is to be judged."""
        assert q.coords is not None and q.pixels is not None
        if q.camera is not None and self.prior and q.intrinsics and self.options.focal_tolerance > 0 \
                and self.map_judges_focal:  # found where first asked for: the features' verdict mostly decides alone
            q.map_focal = Job(estimate_focal, q.pixels, q.coords.reshape(-1, 3), q.camera.width, q.camera.height,
                              q.threshold, self.seed, background=False).result
        if q.camera is not None and self.prior:
            q.dense = solve_pnp(q.pixels, q.coords.reshape(-1, 3), q.camera, max_error_px=q.threshold,
                                seed=self.seed, min_inliers=self.options.min_inliers, backend=self.options.backend)
        else:  # no learned pose (prior=none, or no focal length from the map): features may still find one
            q.dense = PnPResult(False, nan_R(), nan_t(), np.zeros(0, bool), 0, 0.0)
        q.t3 = time.perf_counter()
        q.R, q.t, q.inliers = q.dense.R, q.dense.t, q.dense.num_inliers  # the answer, unless refinement finds a better

    def _refine_by_keypoints(self, q: Query) -> None:
        """Keypoint-guided refinement of the learned pose (refine=keypoints, paper §3.2.2)."""
        assert self.keypoints_xyz is not None and q.dense is not None and q.coords is not None
        ref = refine_pose(q.pixels, q.coords.reshape(-1, 3), q.camera, self.keypoints_xyz, q.dense.R, q.dense.t,
                          max_error_px=q.threshold, median_depth=self.median_depth,
                          options=self.refine_options, backend=self.options.backend,
                          seed=self.seed, min_inliers=self.options.min_inliers)
        q.iterations, q.kept = ref.iterations, ref.kept
        if ref.kept:
            q.R, q.t, q.inliers, q.path = ref.R, ref.t, ref.final_inliers, "keypoints"

    def _refine_by_features(self, q: Query, found: PhotoFeatures) -> None:
        """The answer from the photo's features (`FeaturePath.answer`) where the verdicts on it let it
        stand: a focal length of a photo without intrinsics that something supports, a given one
        that the evidence does not contradict, support beyond matches by chance."""
        assert self.features is not None and q.dense is not None and q.coords is not None
        w, h = q.width, q.height
        if q.full_camera is None:  # COLMAP's prior for a photo without calibration
            q.full_camera = Camera("SIMPLE_PINHOLE", w, h, (1.2 * max(w, h), w / 2, h / 2))
            q.given = q.full_camera
        feature, rejected, q.full_camera, evidence = self.features.answer(found, q.full_camera, q.dense,
                                                                          q.intrinsics, q.source)
        q.feature = feature
        if not q.intrinsics and feature.success and not rejected and not evidence.focal_estimated \
                and not (q.camera is not None and q.dense.num_inliers >= self.options.min_confidence * q.cells):
            rejected = unsupported_focal(q.full_camera, q.dense.num_inliers, q.cells, q.camera is not None,
                                         self.options)
        if not q.intrinsics and feature.success and not rejected:
            q.given = q.full_camera  # the focal length the features estimated with the pose
        if rejected == FOCAL_UNOBSERVABLE:
            rejected = self._focal_without_global_evidence(q, feature, evidence)
            if rejected == FOCAL_UNOBSERVABLE:  # nothing tells: the answer stands, with a doubt
                rejected = ""
                q.warnings.append(FOCAL_UNCHECKED if self.map_judges_focal else FOCAL_UNCHECKED_MAP)
        if feature.success and not rejected:
            q.R, q.t, q.path = feature.R, feature.t, feature.path
            if q.camera is not None:  # the dense support of the final pose, for `confidence`
                q.inliers = int(reprojection_inliers(q.camera, q.pixels, q.coords.reshape(-1, 3), q.R, q.t,
                                                     q.threshold).sum())
            q.rejected = features_alone_verdict(q.path, feature.inliers, q.inliers, q.cells, self.options)
        elif rejected:
            q.rejected = rejected

    def _dense_verdict(self, q: Query) -> str:
        """Why the learned pose is no answer ("" when it stands) where it is the answer (no landmarks,
        or no feature pose): its own evidence judges it."""
        assert q.dense is not None and q.coords is not None
        rejected = ""
        if q.intrinsics and self.options.focal_tolerance > 0 and not self.map_judges_focal:
            q.warnings.append(MAP_DOES_NOT_JUDGE)
        elif q.intrinsics and self.options.focal_tolerance > 0:
            rejected = self._focal_disagreement(q)
        elif not q.intrinsics:  # a square-pixel focal estimated: stretched?
            rejected = stretch_verdict(q.pixels, q.coords.reshape(-1, 3), q.camera, q.dense.R, q.dense.t, q.threshold)
        if not rejected and q.inliers < self.options.min_confidence * q.cells:
            # a pose, but one that too few cells agree with: wrong answers look like this
            rejected = f"confidence {q.inliers / q.cells:.3f} < min_confidence {self.options.min_confidence:g}"
        return rejected

    def _focal_disagreement(self, q: Query, tolerance: float | None = None) -> str:
        """Why the given focal length cannot be right ("" when it can): the map's scene coordinates
        imply another one (beyond `tolerance`, default focal_tolerance). A wrong focal length can
        still explain most cells with a wrong pose (a shallow view trades focal length for
        distance), so confidence alone cannot catch it. The map's estimate is `q.map_focal`'s where
        it was readied (`_learned_pose`)."""
        assert q.camera is not None and q.coords is not None
        tolerance = self.options.focal_tolerance if tolerance is None else tolerance
        estimate = q.map_focal() if q.map_focal is not None else estimate_focal(
            q.pixels, q.coords.reshape(-1, 3), q.camera.width, q.camera.height, q.threshold, self.seed)
        if estimate is None:
            return ""  # no opinion: nothing to hold against the given focal length
        given = float(np.sqrt(q.camera.focal[0] * q.camera.focal[1]))
        ratio = estimate.params[0] / given
        if abs(np.log(ratio)) <= np.log1p(tolerance):
            return ""
        return focal_reason("the image implies", ratio, tolerance, q.source)

    def _focal_without_global_evidence(self, q: Query, feature: FeatureResult, evidence: QueryEvidence) -> str:
        """Why the given focal length is wrong ("" when it is right, FOCAL_UNOBSERVABLE when nothing
        tells) when the matches to every landmark cannot tell, from the next evidence in order: the
        map's coordinates where they read this photo well (the learned pose agrees with the features' and min_confidence of the
        cells agree with it); else SIFT + PnP's verified matches (P4Pf); else the map's coordinates
        where the learned pose at least agrees with the features'. The map judges at a wider
        tolerance since it is coarse ((1 + tol)^2 - 1: 0.56 at 0.25, so a 2x wrong focal still
        fails); a photo it cannot read (turned sideways) gives it no say, nor does a map that does
        not tell its own views' focal lengths within the tolerance (`map_judges_focal`)."""
        assert self.features is not None and q.dense is not None
        if not self.map_judges_focal:  # a shallow view of a map that cannot judge: SIFT + PnP's matches
            return FOCAL_UNOBSERVABLE  # would cost a second and cannot tell either (docs/confidence.md)
        dense = q.dense
        agree = bool(self.prior and dense.success and feature.success and q.camera is not None
                     and poses_agree(dense.R, dense.t, feature.R, feature.t, self.median_depth))
        wide = (1.0 + self.options.focal_tolerance) ** 2 - 1.0
        if agree and dense.num_inliers >= self.options.min_confidence * q.cells:
            return self._focal_disagreement(q, wide)
        verdict = self.features.focal_verdict(evidence, q.source, verified=True)
        feature.verified, feature.verified_seconds = evidence.verified_record(), evidence.verified_seconds()
        if verdict != FOCAL_UNOBSERVABLE:
            return verdict
        if agree:
            return self._focal_disagreement(q, wide)
        return FOCAL_UNOBSERVABLE  # nothing tells: nothing contradicts the given focal length either

    def _extent(self) -> tuple[np.ndarray, float] | None:
        """The map's centre and radius (map_extent) from its landmarks, else its 3D keypoints; once."""
        if not hasattr(self, "_map_extent"):
            xyz = self.landmarks.xyz if self.landmarks is not None else self.keypoints_xyz
            self._map_extent = map_extent(xyz)
        return self._map_extent
