"""How the two threads of one query share the cores.

With more than one thread, a query's side work (the photo's SIFT, its matches to every landmark,
the focal verdicts: `usvc.relocalize.feature_job`) runs on a worker thread while the main thread
runs the network, the PnP and the guided passes. Left alone, each library would run its own pool
of `threads` threads on each side: torch's for the network, OpenCV's inside the SIFT, OpenBLAS's
inside every descriptor product, so on two cores four to six threads fight for two, and
OpenBLAS's threads spin while they wait for work, taking the core the other side needs.

So while a query's side work runs beside it, the threads are split (`split`): the network runs
on torch's threads less the side's share, and OpenCV and BLAS on the side's share (one thread
each on two cores). Each thread then keeps a core of its own. The split is the same every time
for a given thread count, so the answers are the same bits every run; on two cores they are
those of `threads=1` (every library on one thread), only computed on two cores at once.

The thread pools are the process's: the first query that enters sets them, the last that leaves
puts them back as they were, so queries overlapping in several threads of a process agree.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager

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


def side_libraries(threads: int) -> AbstractContextManager[None]:
    """OpenCV's and BLAS's pools at `threads` while any query is inside; then as they were."""
    import cv2

    def apply() -> Callable[[], None]:
        before = cv2.getNumThreads()
        cv2.setNumThreads(threads)
        blas = _blas().limit(limits=threads)  # puts the limits back when told

        def undo() -> None:
            cv2.setNumThreads(before)
            blas.restore_original_limits()
        return undo

    return _shared("libraries", apply)


def network_threads(threads: int) -> AbstractContextManager[None]:
    """torch's intra-op pool at `threads` while any query's network is inside; then as it was."""
    import torch

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
    """A query on `threads` threads whose side work runs beside it: OpenCV and BLAS at the side's
    share meanwhile, and `for_network` (on this thread) at the network's."""
    network, side = split(threads)
    before = getattr(_LOCAL, "network", None)
    with side_libraries(side):
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
