"""A query's two threads: its side work on a worker thread (`Job`), and how the two share the cores.

Refinement by features needs the photo's SIFT keypoints and, for the focal-length verdict (or when
the learned pose misses), their matches to every landmark; neither depends on the learned pose.
The map's own focal-length estimate (P4Pf on its coordinates) needs only the network's output.
With more than one thread (torch's count), each is computed on a worker thread as soon as its
inputs exist (`Job`), while the main thread runs the network, the PnP and the guided passes: the
same functions on the same inputs, so the same keypoints, matches and estimates, in less wall time
(OpenCV, BLAS, COLMAP and torch release the GIL). With one thread each is computed in place, only
when asked for, as it is on a thread that `inline_jobs` marks (one of several queries running at
once, `usvc.relocalize.photo_batch`: they would all queue on the one worker).

Left alone, each library would run its own pool of `threads` threads on each side: torch's for the
network, OpenCV's inside the SIFT, OpenBLAS's inside every descriptor product, so on two cores four
to six threads fight for two, and OpenBLAS's threads spin while they wait for work, taking the core
the other side needs.

So while a query's side work runs beside it, the threads are split (`split`): the network runs
on torch's threads less the side's share, and BLAS on the side's share (one thread each on two
cores). OpenCV keeps all of the query's threads: its SIFT is the side's longest work and outlasts
the network and the learned pose (on the room at 960 frames 45 ms on one thread, 27 on two,
against ~25 ms), so once they are done it takes the main thread's core too, where the main thread
would only wait for it (5-6 ms off a query there, docs/speed.md); the main thread's own OpenCV calls
meanwhile run no parallel loops that matter. The split is the same every time for a given thread
count, so the answers are the same bits every run; on two cores they are those of `threads=1`
(every library on one thread: OpenCV's SIFT gives the same keypoints on any count), only computed
on two cores at once.

The thread pools are the process's: the first query that enters sets them, the last that leaves
puts them back as they were, so queries overlapping in several threads of a process agree.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager
from typing import Any, TypeVar

import torch

_LOCK = threading.Lock()
_LOCAL = threading.local()  # .network: the network's threads in the query this thread runs, when split
_STATE = {"libraries": 0, "torch": 0}  # queries inside each context now
_UNDO: dict[str, Callable[[], None]] = {}  # how to put each back


def split(threads: int) -> tuple[int, int]:
    """(the network's threads, the side's threads) of a query run on `threads` threads: the side
    (OpenCV's SIFT, BLAS's products) gets half, at least one; the network the rest, at least one."""
    side = max(1, threads // 2)
    return max(1, threads - side), side


@functools.lru_cache(maxsize=1)
def _blas():
    """threadpoolctl's view of the BLAS libraries loaded now (numpy's OpenBLAS), found once."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController().select(user_api="blas")


@contextmanager
def _shared(name: str, apply: Callable[[], Callable[[], None]]) -> Iterator[None]:
    """`apply()` (which returns how to undo itself) when the first query enters `name`; the undo
    when the last one leaves: overlapping queries set a pool once and put it back once."""
    with _LOCK:
        if _STATE[name] == 0:
            _UNDO[name] = apply()
        _STATE[name] += 1
    try:
        yield
    finally:
        with _LOCK:
            _STATE[name] -= 1
            if _STATE[name] == 0:
                _UNDO.pop(name)()


def side_libraries(threads: int, opencv: int | None = None) -> AbstractContextManager[None]:
    """OpenCV's and BLAS's pools at `threads` (OpenCV's at `opencv` where given) while any query is
    inside; then as they were."""
    import cv2

    def apply() -> Callable[[], None]:
        before = cv2.getNumThreads()
        cv2.setNumThreads(threads if opencv is None else opencv)
        blas = _blas().limit(limits=threads)  # puts the limits back when told

        def undo() -> None:
            cv2.setNumThreads(before)
            blas.restore_original_limits()
        return undo

    return _shared("libraries", apply)


def network_threads(threads: int) -> AbstractContextManager[None]:
    """torch's intra-op pool at `threads` while any query's network is inside; then as it was."""
    def apply() -> Callable[[], None]:
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        return lambda: torch.set_num_threads(before)

    return _shared("torch", apply)


def products_on_own_threads() -> AbstractContextManager[None]:
    """torch's pool at one thread while the per-image products run on the query's own threads
    (`verified_matching`: each of those threads a core of its own, as with the side split); shared
    with overlapping queries as `network_threads` is."""
    return network_threads(1)


@contextmanager
def query_split(threads: int) -> Iterator[None]:
    """A query on `threads` threads whose side work runs beside it: BLAS at the side's share
    meanwhile, OpenCV (the side's SIFT) at all `threads`, and `for_network` (on this thread) at the
    network's."""
    network, side = split(threads)
    before = getattr(_LOCAL, "network", None)
    with side_libraries(side, opencv=threads):
        _LOCAL.network = network
        try:
            yield
        finally:
            _LOCAL.network = before


@contextmanager
def for_network() -> Iterator[None]:
    """torch's pool at the network's share of the query this thread runs in `query_split`; as it is
    outside one."""
    network = getattr(_LOCAL, "network", None)
    if network is None:
        yield
        return
    with network_threads(network):
        yield


# The side work: jobs on the process's one worker thread, in the order they were started.
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
