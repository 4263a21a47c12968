"""Work on a few threads at once, results in the order of the work: for per-photo steps whose
results must not depend on the thread count (each item is computed alone, then consumed in order)."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int, *, ahead: int = 2,
                name: str = "usvc-work") -> Iterator[tuple[T, R]]:
    """(item, fn(item)) in the order of `items`, with up to `workers` calls running side by side and
    at most `ahead` x `workers` results held that were not handed out yet (memory stays bounded on
    captures of thousands of photos). One worker calls `fn` on this thread, one item at a time. An
    item's exception is raised when its turn comes; later items may have run by then."""
    if workers <= 1:
        for item in items:
            yield item, fn(item)
        return
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name) as pool:
        pending: deque = deque()
        try:
            for item in items:
                pending.append((item, pool.submit(fn, item)))
                if len(pending) > ahead * workers:
                    first, job = pending.popleft()
                    yield first, job.result()
            while pending:
                first, job = pending.popleft()
                yield first, job.result()
        finally:
            for _, job in pending:  # an error or an abandoned loop: run nothing more
                job.cancel()


@contextmanager
def library_threads(get: Callable[[], int], set_: Callable[[int], object], count: int) -> Iterator[None]:
    """A library's own thread pool (torch's, OpenCV's) held at `count` threads, then set back: one
    each while `ordered_map` runs items side by side."""
    before = get()
    set_(count)
    try:
        yield
    finally:
        set_(before)
