"""Localize work on a bounded pool of threads: at most `threads` run and `queue` wait; one more
is refused at once (503 with Retry-After) rather than piling up. A request that waits and runs
longer than its time limit is answered 504; its work, once started, finishes in the background
(a thread cannot be stopped) and its slot stays taken until then, so a burst of slow photos is
refused rather than run beside the abandoned ones."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from usvc.serve.errors import ApiError

T = TypeVar("T")


class WorkPool:
    def __init__(self, threads: int, queue: int, retry_after_s: int = 1) -> None:
        self.threads, self.capacity, self.retry_after_s = threads, threads + queue, retry_after_s
        self._executor = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="usvc-serve")
        self._lock = threading.Lock()
        self.admitted = 0  # waiting + running + abandoned-but-running
        self.waiting = 0
        self.running = 0
        self.abandoned = 0

    def state(self) -> dict[str, int]:
        with self._lock:
            return {"waiting": self.waiting, "running": self.running, "abandoned": self.abandoned}

    def _busy(self) -> ApiError:
        return ApiError("busy", f"the server is busy ({self.admitted} requests admitted, {self.threads} running "
                        f"at a time): retry after {self.retry_after_s} s", headers={"Retry-After": str(self.retry_after_s)})

    def check_room(self) -> None:
        """ApiError busy now if no request could be admitted (before a request's body is read)."""
        with self._lock:
            if self.admitted >= self.capacity:
                raise self._busy()

    def _admit(self) -> None:
        with self._lock:
            if self.admitted >= self.capacity:
                raise self._busy()
            self.admitted += 1
            self.waiting += 1

    async def run(self, fn: Callable[[], T], timeout_s: float) -> T:
        """fn() on a worker thread, within `timeout_s` of admission; ApiError busy / timeout."""
        self._admit()
        abandoned = threading.Event()

        def job() -> T:
            with self._lock:
                self.waiting -= 1
                self.running += 1
            try:
                return fn()
            finally:
                with self._lock:
                    self.running -= 1

        def release(fut: Future) -> None:
            with self._lock:
                self.admitted -= 1
                if fut.cancelled():  # never started
                    self.waiting -= 1
                if abandoned.is_set() and not fut.cancelled():
                    self.abandoned -= 1

        try:
            fut = self._executor.submit(job)
        except RuntimeError:  # shutting down
            with self._lock:
                self.admitted -= 1
                self.waiting -= 1
            raise ApiError("busy", "the server is shutting down", headers={"Retry-After": str(self.retry_after_s)}) \
                from None
        fut.add_done_callback(release)
        wrapped = asyncio.wrap_future(fut)
        done, _ = await asyncio.wait({wrapped}, timeout=timeout_s)
        if not done:
            if not fut.cancel():
                with self._lock:
                    if not fut.done():
                        abandoned.set()
                        self.abandoned += 1
            wrapped.add_done_callback(_consume)  # its outcome (an error too) is dropped quietly
            raise ApiError("timeout", f"no answer within the {timeout_s:g} s time limit of a request")
        return wrapped.result()

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


def _consume(fut: asyncio.Future) -> None:
    if not fut.cancelled():
        fut.exception()
