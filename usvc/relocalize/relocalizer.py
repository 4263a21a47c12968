"""Localize one photo against a trained map: dense scene coordinates -> RANSAC-PnP -> pose, then
refinement: by features (relocalize.refine=features: the query's SIFT keypoints matched to the
map's landmarks, guided by that pose, LO-RANSAC PnP; matching against every landmark when the
learned pose is missing or too far off) or keypoint-guided (paper §3.2.2, refine=keypoints).

This is the one implementation behind the relocalize stage, the Python API and `usvc localize`,
so benchmark numbers and real use cannot drift apart.
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
from usvc.core.geometry import camera_centers
from usvc.core.images import Photo, read_photo
from usvc.core.options import check
from usvc.core.precision import autocast, resolve_precision
from usvc.core.scene import Camera
from usvc.core.sift_grey import colmap_grey
from usvc.core.undistort import undistort
from usvc.landmarks.landmark_table import Landmarks
from usvc.landmarks.landmarks_file import landmarks_beside, landmarks_disagree, read_landmarks
from usvc.model.encoder import cell_centers
from usvc.model.head import Regressor
from usvc.model.map_file import load_map, map_keypoints, read_map_header
from usvc.model.preprocess import normalise, resize_to_short_side
from usvc.relocalize.options import REFERENCE_SHORT_SIDE, RelocalizeOptions
from usvc.relocalize.answer_checks import (  # noqa: F401 (re-exported)
    FAR_RADII, UNGUIDED_PATHS, far_camera_verdict, features_alone_verdict, map_extent)
from usvc.relocalize.feature_job import Job, feature_job, global_match_job, runs_beside
from usvc.relocalize.byte_products import ByteRows, scaled
from usvc.relocalize.device_matching import matching_device
from usvc.relocalize.feature_answer import FeatureAnswers
from usvc.relocalize.feature_refinement import FeatureResult
from usvc.relocalize.image_retrieval import ImageRetrieval, Retrieved
from usvc.relocalize.focal_verdicts import (
    FOCAL_UNCHECKED,
    FOCAL_UNCHECKED_MAP,
    FOCAL_UNOBSERVABLE,
    MAP_DOES_NOT_JUDGE,
    FocalVerdicts,
)
from usvc.relocalize.pnp import PnPResult, reprojection_inliers, solve_pnp
from usvc.relocalize.camera_checks import (
    FOCAL_SPREAD,
    intrinsics_warnings,
    implausible_focal,
    stretch_verdict,
)
from usvc.relocalize.pose_estimate import PoseEstimate, nan_R, nan_t
from usvc.relocalize.query_features import choose_sift
from usvc.relocalize.query_input import Intrinsics, as_gray, camera_from_intrinsics, check_device
from usvc.relocalize.photo_batch import check_workers, in_order, query_threads, threads_per_query
from usvc.relocalize.photo_processes import RelocalizerArgs, in_processes
from usvc.relocalize.query_cores import for_network, query_split
from usvc.relocalize.refinement import RefineOptions, refine_pose
from usvc.relocalize.verified_matching import HeldKeypointDescriptors, observation_descriptors
from usvc.weights import WEIGHTS_DIR, load_configured_encoder

log = logging.getLogger(__name__)

MIN_IMAGE_SIDE = 32
MAX_ASPECT = 4  # long side / short side of a query photo (phones: 1.3-2.2)
# A photo below this contrast (std of its grey levels in [0, 1]) is blank: nothing to localize.
MIN_CONTRAST = 1.0 / 255.0

CAMERA_FOV = "crop"  # a distorted query is undistorted as prepare undistorts mapping images
FEATURE_PATHS = ("guided", "global", "verified")  # answers that came from the photo's features


def refine_options(options: RelocalizeOptions) -> RefineOptions:
    return RefineOptions(radius_px=options.refine_radius_px, max_iterations=options.refine_max_iterations,
                         delta=options.refine_delta, min_correspondences=options.refine_min_correspondences)


class Relocalizer(FeatureAnswers, FocalVerdicts):
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
        width = float(header["encoder"].get("width", 1.0))
        kind = str(header["encoder"].get("kind", "ace"))
        if encoder_weights is None:  # the shipped file the map was trained with (e.g. model=small_real)
            recorded = header["metadata"].get("encoder_file")
            if isinstance(recorded, str) and kind == "ace" and (WEIGHTS_DIR / Path(recorded).name).is_file():
                encoder_weights = WEIGHTS_DIR / Path(recorded).name
        encoder, _ = load_configured_encoder(width, encoder_weights, kind)
        self.regressor: Regressor
        self.regressor, self.metadata = load_map(map_path, encoder, header)
        self.regressor.to(device).eval()
        self.device = device
        # The map's weights are stored at fp16 whatever precision it was trained at, so any map runs
        # at either precision on any machine.
        self.precision = resolve_precision(self.options.precision, device)
        # bf16 on a CPU: oneDNN's convolutions run faster in the channels-last layout (the network alone
        # 18-20 against 20-24 ms on mini's map, 20-22 against 23-30 on bird's; docs/speed.md); fp32 did not gain
        self.memory_format = torch.channels_last if self.precision == "bf16" and torch.device(device).type == "cpu" \
            else torch.contiguous_format
        self.regressor.to(memory_format=self.memory_format)
        self.sift = choose_sift(self.options.features_extractor, device, self.options.prior)  # the query's SIFT, and where it runs
        if "short_side" not in self.metadata:
            raise UsvcError(f"map file {map_path} has no metadata field 'short_side' (the image size its head "
                            "was trained at): not a map the train stage wrote")
        self.short_side = int(self.metadata["short_side"])  # checked on load: an integer in range
        self.map_path = Path(map_path)
        # what a worker process needs to make the same relocalizer (`localize_many(processes=True)`): the
        # precision as resolved here, since `auto` times the products (a process starting beside others could
        # find them otherwise)
        self.args = RelocalizerArgs(self.map_path, None if encoder_weights is None else Path(encoder_weights),
                                    replace(self.options, precision=self.precision), device, seed,
                                    None if landmarks is None else Path(landmarks))
        spread = self.metadata.get("focal_range")  # checked on load; maps before it have none
        self.focal_range = (float(spread[0]), float(spread[1])) if spread is not None else None
        # The map judges a given focal length only if it tells its own views' within the tolerance
        # (usvc.train.focal_calibration; maps before that measure judge, as they did)
        error = self.metadata.get("focal_error")
        self.map_judges_focal = bool(error is None or float(error) <= np.log1p(self.options.focal_tolerance))
        if not self.map_judges_focal and self.options.focal_tolerance > 0:
            log.info("map %s implies its own views' focal lengths only within %.0f %% (90th percentile), over "
                     "focal_tolerance %g: the map does not judge given focal lengths, the photos' features do",
                     map_path, 100 * (np.exp(float(error)) - 1), self.options.focal_tolerance)
        self.keypoints_xyz = map_keypoints(header)
        depth = self.metadata.get("median_depth")
        self.median_depth = float(depth) if isinstance(depth, (int, float)) and np.isfinite(depth) and depth > 0 else 1.0
        self.refine_options = refine_options(self.options)
        self.refine = self.options.refine == "keypoints" and self.keypoints_xyz is not None
        if self.options.refine == "keypoints" and self.keypoints_xyz is None:
            log.warning("map %s has no 3D keypoints: keypoint-guided refinement is off", self.map_path)
        self.landmarks: Landmarks | None = None
        self.landmarks_path: Path | None = None
        self.prior = self.options.prior == "learned"  # prior=none: the learned pose guides nothing
        if not self.prior and self.options.refine != "features":
            raise UsvcError(f"relocalize.prior=none needs relocalize.refine=features (got {self.options.refine!r}): "
                            "without the learned pose only the photo's features can give a pose")
        if self.options.refine == "features":
            self._load_landmarks(landmarks)

    def _load_landmarks(self, landmarks: str | Path | None) -> None:
        """Read and check the map's landmarks; a map without them localizes without refinement."""
        if landmarks is not None and not isinstance(landmarks, (str, Path)):
            raise UsvcError(f"landmarks must be the path of a landmarks.h5, got {type(landmarks).__name__}")
        path = Path(landmarks) if landmarks is not None else landmarks_beside(self.map_path)
        if path is None:
            if not self.prior:
                raise UsvcError(f"relocalize.prior=none needs the map's landmarks, and map {self.map_path} has none "
                                "beside it (landmarks.h5; --landmarks names it)")
            log.warning("map %s has no landmarks beside it (landmarks.h5): refinement by features is off",
                        self.map_path)
            return
        found = read_landmarks(path)
        why = landmarks_disagree(found, self.metadata.get("scene"), self.keypoints_xyz)
        if why:
            raise UsvcError(f"{path} are not the landmarks of map {self.map_path}: {why}")
        self.landmarks, self.landmarks_path = found, path
        self._landmark_desc = scaled(found.descriptor)  # matched by COLMAP's integer dots (`byte_products`)
        self._landmark_bytes = ByteRows.of(found.descriptor)
        self._observation_desc = observation_descriptors(found.observations) if found.observations is not None \
            else None
        self._keypoint_desc = HeldKeypointDescriptors(found.observations)  # SIFT + PnP's matching reads them
        self._retrieval = ImageRetrieval(found)  # the mapping photos most like a query
        if not self.prior and found.observations is None:
            raise UsvcError(f"relocalize.prior=none needs landmarks with their observations; {path} has none "
                            "(format version 1): rebuild them with the landmarks stage")

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

    @torch.inference_mode()
    def scene_coordinates(self, gray01: np.ndarray) -> np.ndarray:
        """(h, w, 3) world coordinates of the image's 8x8 cells, as float64."""
        with autocast(self.precision, self.device), for_network():
            image = normalise(gray01).to(self.device).contiguous(memory_format=self.memory_format)
            out = self.regressor(image)[0].float()
        return out.permute(1, 2, 0).double().cpu().numpy()

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
        if self.landmarks is not None and runs_beside():  # side work on the worker thread: the threads are
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
        t0 = time.perf_counter()
        gray = as_gray(image, channels)  # the network's luma (checks the array too)
        # COLMAP's SIFT on the grey COLMAP's reader makes, as the sfm stage extracted the mapping photos
        # (`sift_grey`); OpenCV's on the luma, as `sfm.extractor=opencv` extracts them
        sift_gray = colmap_grey(np.asarray(image), rgb=channels == "rgb").astype(np.float32) / 255.0 \
            if self.landmarks is not None and self.sift.kind == "colmap" else gray
        h, w = gray.shape
        if min(h, w) < MIN_IMAGE_SIDE:
            raise UsvcError(f"image is {w}x{h}; need at least {MIN_IMAGE_SIDE} px on each side")
        if max(h, w) > MAX_ASPECT * min(h, w):
            raise UsvcError(f"image is {w}x{h}, an aspect ratio of {max(h, w) / min(h, w):.1f}:1; usvc localizes "
                            f"photos up to {MAX_ASPECT}:1 (a strip or panorama is not a camera view it can map)")
        given = None if intrinsics is None else camera_from_intrinsics(intrinsics, w, h)
        warnings = intrinsics_warnings(given) if given is not None else []
        for line in warnings:
            log.warning("%s", line)
        early = ""  # a reason to answer without looking: a blank photo, a focal length no camera has
        if float(gray.std()) < MIN_CONTRAST:
            early = (f"the photo is blank (its grey levels vary by {255 * float(gray.std()):.2g} of 255): "
                     "nothing to localize")
        elif given is not None:
            focal = float(np.sqrt(given.focal[0] * given.focal[1]))
            early = implausible_focal(focal, w, h, intrinsics_source or f"the given focal length ({focal:.4g} px)")
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
        full_gray, full_camera = sift_gray, camera  # undistorted, at the photo's size: what features see
        job = None  # the photo's features, found on a second thread while the network runs
        if self.landmarks is not None:
            job = feature_job(full_gray, self.landmarks.image_short_side, self.options.features_max_keypoints,
                              self.sift)
        gray, resize = self.working_image(gray)
        if resize != 1.0 and camera is not None:
            camera = camera.scaled(gray.shape[1], gray.shape[0])
        t1 = time.perf_counter()
        coords = self.scene_coordinates(gray)
        t2 = time.perf_counter()
        hc, wc = coords.shape[:2]
        # Scale the threshold with the working resolution: 10 px at 480 px is 5 px at 240 px.
        threshold = self.options.max_error_px * min(gray.shape) / REFERENCE_SHORT_SIDE
        pixels = cell_centers(hc, wc, "colmap").permute(1, 2, 0).reshape(-1, 2).double().numpy()
        no_focal = ""  # why the map's coordinates gave no focal length, when the photo has none
        if camera is None and self.prior:
            camera = estimate_focal(pixels, coords.reshape(-1, 3), gray.shape[1], gray.shape[0], threshold,
                                    self.seed)
            if camera is None:
                no_focal = ("no camera explains the map's scene coordinates of this photo, so its focal length "
                            "cannot be estimated: not a view of this map's scene (or too dark or blurred?)")
            else:
                f = camera.params[0] / resize
                no_focal = implausible_focal(f, w, h, f"the focal length estimated with the pose ({f:.4g} px)")
                ratio, lo_hi = f / max(w, h), self.focal_range
                if not no_focal and lo_hi and not lo_hi[0] / FOCAL_SPREAD <= ratio <= lo_hi[1] * FOCAL_SPREAD:
                    no_focal = (f"the focal length estimated with the pose ({f:.4g} px, {ratio:.2f}x the long side) "
                                f"is over {FOCAL_SPREAD:g}x off the map's cameras' ({lo_hi[0]:.2f}-{lo_hi[1]:.2f}x)")
                if no_focal:  # the map does not read this photo: its dense answer is no answer
                    no_focal += ": the map does not recognise this photo (another place, or stretched or cropped?)"
                    camera = None
                else:
                    given = Camera("SIMPLE_PINHOLE", w, h, (f, w / 2, h / 2))
                    full_camera = given
        if camera is None and self.landmarks is None:
            t3 = time.perf_counter()
            seconds = {"preprocess": t1 - t0, "network": t2 - t1, "pnp": t3 - t2, "refine": 0.0, "total": t3 - t0}
            return PoseEstimate(False, nan_R(), nan_t(), 0, hc * wc, seconds, focal_estimated=True,
                                rejected=no_focal, warnings=warnings, pose_found=False)
        map_focal = None  # the map's own estimate of the focal length (P4Pf on its coordinates) for its verdicts:
        if camera is not None and self.prior and intrinsics is not None and self.options.focal_tolerance > 0 \
                and self.map_judges_focal:  # found where first asked for: the features' verdict mostly decides alone
            map_focal = Job(estimate_focal, pixels, coords.reshape(-1, 3), camera.width, camera.height, threshold,
                            self.seed, background=False).result
        if camera is not None and self.prior:
            result = solve_pnp(pixels, coords.reshape(-1, 3), camera, max_error_px=threshold,
                               seed=self.seed, min_inliers=self.options.min_inliers,
                               backend=self.options.backend)
        else:  # no learned pose (prior=none, or no focal length from the map): features may still find one
            result = PnPResult(False, nan_R(), nan_t(), np.zeros(0, bool), 0, 0.0)
        t3 = time.perf_counter()
        found_set, global_pairs, retrieved = None, None, Retrieved()
        if job is not None:  # the features, and (on the worker, while the guided passes run) their matches
            found_set = job.result()  # to every landmark (retrieved) where a verdict or a fallback needs them
            if self.prior:  # the mapping photos most like it bound those matches and the fallback: `image_retrieval`
                retrieved = self._retrieval.retrieve(found_set.feats, self.options.features_retrieval_images)
            if self.prior and (intrinsics is None or self.options.focal_tolerance > 0):
                global_pairs = global_match_job(self._landmark_desc, found_set.feats, self.options.features_ratio,
                                                matching_device(self.device), landmark_bytes=self._landmark_bytes,
                                                rows=retrieved.landmarks).result
        # Evidence before verdicts: the learned pose is a hypothesis. No check on it refuses the photo
        # before the features have had their say; the checks below judge the final answer with the
        # evidence that produced it.
        R, t, inliers, iterations, kept = result.R, result.t, result.num_inliers, 0, False
        path, feature, rejected = "dense", None, ""
        if result.success and self.refine:
            assert self.keypoints_xyz is not None
            ref = refine_pose(pixels, coords.reshape(-1, 3), camera, self.keypoints_xyz, result.R, result.t,
                              max_error_px=threshold, median_depth=self.median_depth,
                              options=self.refine_options, backend=self.options.backend,
                              seed=self.seed, min_inliers=self.options.min_inliers)
            iterations, kept = ref.iterations, ref.kept
            if kept:
                R, t, inliers, path = ref.R, ref.t, ref.final_inliers, "keypoints"
        if self.landmarks is not None:
            if full_camera is None:  # COLMAP's prior for a photo without calibration
                full_camera = Camera("SIMPLE_PINHOLE", w, h, (1.2 * max(w, h), w / 2, h / 2))
                given = full_camera
            assert found_set is not None
            feature, feature_rejected, full_camera, feature_evidence = self._features(
                found_set, global_pairs, full_camera, result, intrinsics is not None, intrinsics_source, retrieved)
            if intrinsics is None and feature.success and not feature_rejected and not feature_evidence.focal_estimated \
                    and not (camera is not None and result.num_inliers >= self.options.min_confidence * hc * wc):
                feature_rejected = self._unsupported_focal(full_camera, result.num_inliers, hc * wc, camera is not None)
            if intrinsics is None and feature.success and not feature_rejected:
                given = full_camera  # the focal length the features estimated with the pose
            if feature_rejected == FOCAL_UNOBSERVABLE:
                feature_rejected = self._focal_without_global_evidence(
                    result, feature, feature_evidence, pixels, coords, camera, threshold, hc * wc, intrinsics_source,
                    map_focal)
                if feature_rejected == FOCAL_UNOBSERVABLE:  # nothing tells: the answer stands, with a doubt
                    feature_rejected = ""
                    warnings.append(FOCAL_UNCHECKED if self.map_judges_focal else FOCAL_UNCHECKED_MAP)
            if feature.success and not feature_rejected:
                R, t, path = feature.R, feature.t, feature.path
                if camera is not None:  # the dense support of the final pose, for `confidence`
                    inliers = int(reprojection_inliers(camera, pixels, coords.reshape(-1, 3), R, t, threshold).sum())
                rejected = features_alone_verdict(path, feature.inliers, inliers, hc * wc, self.options)
            elif feature_rejected:
                rejected = feature_rejected
        by_features = path in FEATURE_PATHS
        if result.success and not by_features and not rejected:
            # the learned pose is the answer (no landmarks, or no feature pose): its own evidence judges it
            if intrinsics is not None and self.options.focal_tolerance > 0 and not self.map_judges_focal:
                warnings.append(MAP_DOES_NOT_JUDGE)
            elif intrinsics is not None and self.options.focal_tolerance > 0:
                rejected = self._focal_disagreement(pixels, coords, camera, threshold, source=intrinsics_source,
                                                    map_focal=map_focal)
            elif intrinsics is None:  # a square-pixel focal estimated: stretched?
                rejected = stretch_verdict(pixels, coords.reshape(-1, 3), camera, result.R, result.t, threshold)
            if not rejected and inliers < self.options.min_confidence * hc * wc:
                # a pose, but one that too few cells agree with: wrong answers look like this
                rejected = f"confidence {inliers / (hc * wc):.3f} < min_confidence {self.options.min_confidence:g}"
        t4 = time.perf_counter()
        seconds = {"preprocess": t1 - t0, "network": t2 - t1, "pnp": t3 - t2, "refine": t4 - t3,
                   "total": t4 - t0}
        if feature is not None and feature.verified_seconds is not None:  # SIFT + PnP's matching, part of refine
            seconds["fallback"] = feature.verified_seconds
        if (result.success or by_features) and not rejected:
            rejected = far_camera_verdict(camera_centers(R, t), self._extent())
        success = (result.success or by_features) and not rejected
        pose_found = bool(result.success or (feature is not None and feature.success))
        if not success:
            R, t = nan_R(), nan_t()
            if not rejected:  # every failure says why
                rejected = no_focal or self._no_pose_reason(result, feature, hc * wc)
        return PoseEstimate(success, R, t, inliers, hc * wc, seconds,
                            initial_R=result.R.copy() if success and result.success else nan_R(),
                            initial_t=result.t.copy() if success and result.success else nan_t(),
                            refine_iterations=iterations, refine_kept=kept or by_features, camera=given,
                            focal_estimated=intrinsics is None, rejected=rejected,
                            refine_method=self.options.refine if (self.refine or self.landmarks is not None)
                            else "none", refine_path=path if success else "",
                            feature_inliers=feature.inliers if feature is not None else 0,
                            feature_passes=feature.passes if feature is not None else [],
                            feature_hypotheses=feature.tried if feature is not None else [],
                            verified=feature.verified if feature is not None else None,
                            warnings=warnings, pose_found=pose_found, prior=self.options.prior)

    def _extent(self) -> tuple[np.ndarray, float] | None:
        """The map's centre and radius (map_extent) from its landmarks, else its 3D keypoints; once."""
        if not hasattr(self, "_map_extent"):
            xyz = self.landmarks.xyz if self.landmarks is not None else self.keypoints_xyz
            self._map_extent = map_extent(xyz)
        return self._map_extent

    def _no_pose_reason(self, result: PnPResult, feature: FeatureResult | None, cells: int) -> str:
        """Why neither the map's coordinates nor the features gave a pose."""
        why = (f"no pose: RANSAC-PnP on the map's scene coordinates found none that min_inliers="
               f"{self.options.min_inliers} of the {cells} cells agree with ({result.num_inliers} at best)")
        if feature is not None:
            why += f", and the photo's features gave none ({feature.why or 'no match to the landmarks'})"
        return why + ": not a view of this map's scene, or too dark, blurred or featureless?"
