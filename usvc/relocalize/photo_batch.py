"""Many photos, several at a time: each photo's whole query (decoding included) on one of `workers`
threads, the answers handed out in the photos' order.

One query keeps two cores only partly busy: the guided passes, the PnP and numpy's per-pair work
run on one thread, and two threads make the network only 1.2-1.4x faster. Queries of different
photos share nothing, so on a machine with many cores (or a GPU, which runs each network in a few
milliseconds while the CPU does the rest) several in flight keep every core busy. Each query then
runs with `threads // workers` threads of its own (torch's, OpenCV's and BLAS's pools, set for the batch)
and does its side work in place rather than on the per-process worker thread
(`usvc.relocalize.query_cores.inline_jobs`), so the answers are bit for bit those of the photos
localized one after the other with that many threads."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from usvc.core.errors import UsvcError
from usvc.relocalize.query_cores import inline_jobs, network_threads, side_libraries

T = TypeVar("T")
R = TypeVar("R")
_THREADS_LOCK = threading.Lock()  # one batch at a time sets the process's thread pools


def threads_per_query(threads: int, workers: int) -> int:
    """The threads each of `workers` concurrent queries gets of `threads` (at least one)."""
    return max(1, threads // workers)


def check_workers(workers: object) -> int:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise UsvcError(f"workers must be a whole number >= 1 (photos localized at a time), got {workers!r}")
    return workers


@contextmanager
def query_threads(n: int) -> Iterator[None]:
    """torch's, OpenCV's and BLAS's thread pools at `n` for the duration, then as they were (BLAS
    too: OpenBLAS's idle threads spin, taking the cores the other queries need)."""
    with _THREADS_LOCK, network_threads(n), side_libraries(n):
        yield


def in_order(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """`fn(item)` for every item, `workers` at a time on threads of their own (in place, one after
    the other, for one worker), yielded in the items' order. At most 2 x workers items are started
    ahead of the one handed out, so a long folder is not decoded into memory at once. What `fn`
    raises is raised when its item's turn comes."""
    workers = check_workers(workers)
    if workers == 1:
        yield from map(fn, items)
        return

    def run(item: T) -> R:
        with inline_jobs():
            return fn(item)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="usvc-query") as pool:
        ahead: deque[Future] = deque()
        source = iter(items)
        try:
            for item in source:
                ahead.append(pool.submit(run, item))
                if len(ahead) >= 2 * workers:
                    yield ahead.popleft().result()
            while ahead:
                yield ahead.popleft().result()
        finally:
            for future in ahead:  # the consumer stopped early: start nothing more
                future.cancel()
