"""A query's work that does not wait for the learned pose, done on a second thread.

Refinement by features needs the photo's SIFT keypoints and, for the focal-length verdict (or when
the learned pose misses), their matches to every landmark; neither depends on the learned pose.
The map's own focal-length estimate (P4Pf on its coordinates) needs only the network's output.
With more than one thread (`threads`, torch's count), each is computed on a worker thread as soon
as its inputs exist, while the main thread runs the network, the PnP and the guided passes: the
same functions on the same inputs, so the same keypoints, matches and estimates, in less wall time
(OpenCV, BLAS, COLMAP and torch release the GIL). With one thread each is computed in place, only
when asked for, as it is on a thread that `inline_jobs` marks (one of several queries running at
once, `usvc.relocalize.photo_batch`: they would all queue on the one worker).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch

from usvc.model.preprocess import resize_to_short_side
from usvc.relocalize.byte_products import ByteRows
from usvc.relocalize.feature_refinement import global_matches
from usvc.relocalize.query_features import QueryFeatures, SiftChoice, extract_sift

T = TypeVar("T")
_POOL: ThreadPoolExecutor | None = None
_POOL_PID = 0  # the process that made _POOL: a forked child has none of its threads, so makes its own
_POOL_LOCK = threading.Lock()
_THREAD = threading.local()  # .inline: this thread runs its jobs in place


@contextmanager
def inline_jobs() -> Iterator[None]:
    """Jobs started on this thread meanwhile run in place, when asked for, whatever the thread count."""
    before = getattr(_THREAD, "inline", False)
    _THREAD.inline = True
    try:
        yield
    finally:
        _THREAD.inline = before


def _pool() -> ThreadPoolExecutor:
    """One worker for the whole process: one job at a time, in the order they were started."""
    global _POOL, _POOL_LOCK, _POOL_PID
    if _POOL_PID != os.getpid():  # a fork copies the lock in whatever state it was, not its holder
        _POOL_LOCK = threading.Lock()
    with _POOL_LOCK:
        if _POOL is None or _POOL_PID != os.getpid():
            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="usvc-features")
            _POOL_PID = os.getpid()
        return _POOL


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


def runs_beside() -> bool:
    """Whether a job started now on this thread runs on the worker thread: torch runs on more than
    one thread and this thread is not in `inline_jobs`."""
    return torch.get_num_threads() > 1 and not getattr(_THREAD, "inline", False)


class Job:
    """`fn(*args)`: started at once on the worker thread when `background` (default: torch runs on
    more than one thread and this thread is not in `inline_jobs`), else run in place when `result`
    is first called. Work that may turn out unneeded is started only in the background, where it
    costs no wall time."""

    def __init__(self, fn: Callable[..., T], *args: Any, background: bool | None = None) -> None:
        self._fn, self._args = fn, args
        self._done = False
        self._value: T | None = None
        if background is None:
            background = runs_beside()
        self._future: Future | None = _pool().submit(fn, *args) if background else None

    @property
    def background(self) -> bool:
        return self._future is not None

    def result(self) -> T:
        if not self._done:
            self._value = self._future.result() if self._future is not None else self._fn(*self._args)
            self._done = True
        return self._value  # type: ignore[return-value]


def feature_job(gray01: np.ndarray, short_side: int, max_keypoints: int, extractor: str | SiftChoice,
                background: bool | None = None) -> Job:
    """`find_features` for one photo, as a `Job`."""
    return Job(find_features, gray01, short_side, max_keypoints, extractor, background=background)


def global_match_job(landmark_desc: np.ndarray, feats: QueryFeatures, ratio: float, device: str | None = None,
                     background: bool | None = None, landmark_bytes: ByteRows | None = None,
                     rows: np.ndarray | None = None) -> Job:
    """`global_matches` (the keypoints' matches to every landmark, or to landmark `rows`, products on
    `device`), as a `Job`."""
    return Job(global_matches, landmark_desc, feats, ratio, device, landmark_bytes, rows, background=background)
