"""SIFT features of a query photo, matched against landmarks from the sfm stage's SIFT.

Two extractors: OpenCV's (on the CPU: about 4x faster than COLMAP's there) and COLMAP's own
(pycolmap: the landmarks' exact kind of descriptor), on the CPU or, where pycolmap was built with
CUDA (`pycolmap-cuda12`), on the relocalizer's GPU. OpenCV's runs with COLMAP's detector settings,
so it finds most of COLMAP's keypoints (88-90 % as many on the measured scenes) at COLMAP's
positions, and its descriptors are made L1-root ("RootSIFT") as COLMAP normalises its own; both use
Lowe's descriptor layout, so they match the same landmarks (docs/results.md measures both).
`relocalize.features_extractor: auto` (the default) takes COLMAP's on the GPU where the relocalizer
runs on one that pycolmap can use, else OpenCV's: on a CPU the same features as `opencv`; with
`relocalize.prior=none` (SIFT + PnP's registration) it takes COLMAP's everywhere. Each extractor
sees the grey its mapping-side twin saw: COLMAP's the grey COLMAP's image reader makes
(`usvc.core.sift_grey`: the sfm stage's SIFT reads the photos through it), OpenCV's the luma
(as `sfm.extractor=opencv` converts the photos).
Keypoints use COLMAP's pixel convention (the top-left pixel's centre at (0.5, 0.5)), like every 2D
point in usvc. A query's features are found on the photo resized to the mapping images' short side
when larger (`find_features`), on the worker thread while the network runs (`feature_job`).
"""

from __future__ import annotations

import functools
import logging
import threading
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from usvc.core import opencv_sift
from usvc.core.device import cuda_index
from usvc.landmarks.landmark_table import unit_descriptors
from usvc.model.preprocess import resize_to_short_side
from usvc.relocalize.features.byte_products import scaled
from usvc.relocalize.options import EXTRACTORS
from usvc.relocalize.query_cores import Job

log = logging.getLogger(__name__)
_GPU_LOCKS: defaultdict[int, threading.Lock] = defaultdict(threading.Lock)  # one extraction at a time per GPU


@dataclass(frozen=True)
class QueryFeatures:
    uv: np.ndarray  # (K,2) float64 keypoints, COLMAP pixel convention, in the image they were found in
    descriptor: np.ndarray  # (K,128) float32 unit rows
    codes: np.ndarray | None = None  # (K,128) uint8: COLMAP's encoding of them (default: encoded from `descriptor`,
    # as the sfm stage encodes OpenCV's: `opencv_sift.colmap_descriptors`)
    scaled: np.ndarray = field(init=False, repr=False)  # (K,128) float32: codes / 512, what matching compares

    def __post_init__(self) -> None:
        if self.codes is None:  # every match of the query compares these bytes (`byte_products`)
            object.__setattr__(self, "codes", opencv_sift.colmap_descriptors(self.descriptor).reshape(-1, 128))
        object.__setattr__(self, "scaled", scaled(self.codes))

    def __len__(self) -> int:
        return len(self.uv)


FIRST_OCTAVE = -1  # as the sfm stage extracts (COLMAP's default: the image doubled first); 0 is ~2x faster
# but finds fewer, coarser keypoints (bird: median 3.09 cm / 0.66 deg against 2.48 cm / 0.47 deg)


@dataclass(frozen=True)
class SiftChoice:
    """Which SIFT gives a query's features: `kind` opencv | colmap, and the CUDA device index
    COLMAP's runs on (None: on the CPU)."""

    kind: str
    gpu: int | None = None

    def __str__(self) -> str:
        return self.kind if self.gpu is None else f"{self.kind} (cuda:{self.gpu})"


def pycolmap_has_cuda() -> bool:
    """Whether this pycolmap was built with CUDA (`pycolmap-cuda12`; PyPI's `pycolmap` is CPU-only)."""
    return bool(getattr(pycolmap, "has_cuda", False))


def choose_sift(setting: str, device: str, prior: str = "learned") -> SiftChoice:
    """The query SIFT for `relocalize.features_extractor` = `setting` on a relocalizer whose torch
    device is `device` (resolved: cpu, cuda or cuda:N). COLMAP's runs on that GPU where pycolmap can
    use CUDA; `auto` is then COLMAP's on the GPU, and OpenCV's on the CPU everywhere else, except
    with `relocalize.prior` = `prior` none: that is SIFT + PnP's registration, so `auto` takes its
    own SIFT, COLMAP's, everywhere."""
    if setting not in EXTRACTORS:
        raise ValueError(f"features_extractor={setting!r} is not one of {list(EXTRACTORS)}")
    if setting == "auto" and prior == "none":
        setting = "colmap"
    gpu = None
    if device.startswith("cuda") and setting != "opencv":
        if not pycolmap_has_cuda():
            log.info("the relocalizer runs on %s, but this pycolmap has no CUDA: the query's SIFT runs on the "
                     "CPU (pycolmap-cuda12 runs COLMAP's on the GPU)", device)
        else:
            gpu = cuda_index(device)
            problem = _gpu_sift_problem(gpu)
            if problem:
                log.warning("COLMAP's SIFT does not start on cuda:%d (%s): the query's SIFT runs on the CPU", gpu,
                            problem)
                gpu = None
    if setting == "opencv" or (setting == "auto" and gpu is None):
        return SiftChoice("opencv")
    return SiftChoice("colmap", gpu)


@functools.lru_cache(maxsize=None)
def _gpu_sift_problem(gpu: int) -> str:
    """Why COLMAP's SIFT cannot run on CUDA device `gpu` ("" when it can): making its extractor
    there once tells (without a usable device SiftGPU falls back to OpenGL, and fails headless)."""
    try:
        _extractor(1024, gpu, 1024)
    except Exception as e:  # noqa: BLE001 - pycolmap raises ValueError/RuntimeError from C++ checks
        return str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
    return ""


def _gpu_image_size(height: int, width: int) -> int:
    """COLMAP's GPU SIFT takes images up to its `max_image_size` (its buffers follow that bound):
    the photo's longer side, rounded up to 1,024 px, so that a few extractors serve every size."""
    return -(-max(height, width) // 1024) * 1024


@functools.lru_cache(maxsize=4)
def _extractor(max_features: int, gpu: int | None = None, max_image_size: int = 100_000) -> pycolmap.FeatureExtractor:
    eo = pycolmap.FeatureExtractionOptions()
    eo.sift.max_num_features = max_features
    eo.num_threads = 1  # one image: extraction runs on one thread whatever the setting
    eo.use_gpu = gpu is not None
    eo.max_image_size = max_image_size  # the caller chooses the size (on the CPU: no bound)
    eo.sift.first_octave = FIRST_OCTAVE
    if gpu is None:
        return pycolmap.FeatureExtractor.create(eo, pycolmap.Device.cpu)
    eo.gpu_index = str(gpu)
    return pycolmap.FeatureExtractor.create(eo, pycolmap.Device.cuda)


def extract_sift(gray_u8: np.ndarray, max_features: int, extractor: str | SiftChoice = "opencv") -> QueryFeatures:
    """SIFT keypoints and unit L1-root descriptors of a uint8 grey image (at most `max_features`),
    by `extractor` (a `SiftChoice`, or opencv | colmap on the CPU)."""
    image = np.ascontiguousarray(gray_u8)
    choice = extractor if isinstance(extractor, SiftChoice) else SiftChoice(extractor)
    if choice.kind == "colmap":
        if choice.gpu is None:
            keypoints, descriptors = _extractor(int(max_features)).extract_from_uint8_array(image)
        else:
            size = _gpu_image_size(*image.shape[:2])
            with _GPU_LOCKS[choice.gpu]:  # COLMAP's GPU extractor is not safe for two threads at once
                keypoints, descriptors = _extractor(int(max_features), choice.gpu, size).extract_from_uint8_array(image)
        uv = np.array([(p.x, p.y) for p in keypoints], dtype=np.float64).reshape(-1, 2)
        codes = np.asarray(descriptors.data).reshape(-1, 128)
        return QueryFeatures(uv, unit_descriptors(codes), codes.astype(np.uint8))
    if choice.kind != "opencv" or choice.gpu is not None:
        raise ValueError(f"unknown SIFT extractor {extractor!r}")
    keypoints, unit = opencv_sift.detect(image, max_features)
    return QueryFeatures(opencv_sift.colmap_uv(keypoints), unit)  # its codes: COLMAP's encoding of `unit`


@dataclass
class QueryFeatureSet:
    """The features of one photo: the grey image they were found in (the photo's, resized to the
    landmarks' short side when larger) and its keypoints."""

    gray: np.ndarray
    resized: bool  # whether `gray` is the photo resized (else the photo itself)
    feats: QueryFeatures


def find_features(gray01: np.ndarray, short_side: int, max_keypoints: int,
                  extractor: str | SiftChoice) -> QueryFeatureSet:
    """SIFT (`extractor`, and where it runs) on the photo at most `short_side` px on its short side."""
    resized = min(gray01.shape) > short_side
    if resized:
        gray01, _ = resize_to_short_side(gray01, short_side)
    feats = extract_sift(np.clip(np.rint(gray01 * 255.0), 0, 255).astype(np.uint8), max_keypoints, extractor)
    return QueryFeatureSet(gray01, resized, feats)


def feature_job(gray01: np.ndarray, short_side: int, max_keypoints: int, extractor: str | SiftChoice,
                background: bool | None = None) -> Job:
    """`find_features` for one photo, as a `Job`."""
    return Job(find_features, gray01, short_side, max_keypoints, extractor, background=background)
