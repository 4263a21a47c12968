"""Many photos in worker processes: each process holds its own relocalizer (the map loaded once in
it) and localizes whole photos with `threads // workers` threads; the answers come back in the
photos' order.

Worker threads (`photo_batch`) share one Python interpreter, whose lock a query's Python work (the
matching's bookkeeping, the passes between the products) holds for part of its time, so on a
machine with many cores, or with the network on a GPU, the threads can wait for each other (16
worker threads on a 16-core GPU machine gave 22 photos a second, 5.7 times one at a time; the lock
is the first suspect there). Processes share nothing. The price is each process's start (Python,
torch, the map: 2.2 s on a 2-core CPU, side by side), so they are for folders of hundreds of
photos; on two cores they are no faster than two threads once started (mini the same, bird 8-15 %
slower: docs/speed.md). Workers are spawned, never forked (torch's thread pools and CUDA do not survive a
fork), with the precision the parent resolved; each photo goes to its worker as its path or its
pixels, and its answer comes back as the same `PoseEstimate` the photo gets from a relocalizer of
its own with that many threads, bit for bit.
"""

from __future__ import annotations

import contextlib
import multiprocessing
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from usvc.core.errors import UsvcError
from usvc.relocalize.photo_batch import query_threads
from usvc.relocalize.query_cores import inline_jobs

_WORKER: Any = None  # the worker process's relocalizer, made once by `_start`
_POOLS = contextlib.ExitStack()  # the worker process's thread pool settings, held while it lives


@dataclass(frozen=True)
class RelocalizerArgs:
    """What a worker process needs to make the relocalizer it localizes with: the arguments the
    parent's was made with (its device resolved)."""

    map_path: Path
    encoder_weights: Path | None
    options: Any  # RelocalizeOptions
    device: str
    seed: int
    landmarks: Path | None

    def make(self, cls: Callable[..., Any]) -> Any:
        """The relocalizer of class `cls` (the `Relocalizer` class or a subclass) these arguments make."""
        return cls(self.map_path, self.encoder_weights, self.options, device=self.device, seed=self.seed,
                   landmarks=self.landmarks)


def _start(make: Callable[..., Any], args: RelocalizerArgs, threads: int) -> None:
    """A worker's start: its thread pools (torch's, OpenCV's and BLAS's, for the process's life),
    then its relocalizer (`make`: the class, sent by name)."""
    global _WORKER
    _POOLS.enter_context(query_threads(threads))
    _WORKER = args.make(make)


def _localize(item: tuple[Any, Any, dict]) -> Any:
    """One photo's query, its side work in place (as a worker thread runs it: the process's other
    workers have the other cores); a UsvcError (the photo's own failure) is returned, not raised."""
    image, intrinsics, kwargs = item
    try:
        with inline_jobs():
            return _WORKER.localize(image, intrinsics, **kwargs)
    except UsvcError as err:
        return err


def in_processes(make: Callable[..., Any], args: RelocalizerArgs,
                 items: Iterable[tuple[Any, Any, dict] | UsvcError], workers: int, threads: int,
                 errors: str = "raise") -> Iterator[Any]:
    """`localize(image, intrinsics, **kwargs)` of every item by a relocalizer that `make` (the
    `Relocalizer` class, sent by name) makes from `args` in each of `workers` spawned processes of
    `threads` threads each, yielded in the items' order; at most 2 x workers photos
    are sent ahead of the one handed out. A photo's UsvcError (or an item that is one already: a
    photo known to be unreadable) is raised when its turn comes, or with `errors="return"` handed
    out in its place; a worker that cannot start (or dies) ends the run with one UsvcError."""
    if errors not in ("raise", "return"):
        raise ValueError(f"errors must be 'raise' or 'return', got {errors!r}")

    def handed(result: Any) -> Any:
        if isinstance(result, UsvcError) and errors == "raise":
            raise result
        return result

    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_start,
                             initargs=(make, args, threads)) as pool:
        ahead: deque[Future | UsvcError] = deque()

        def next_out() -> Any:
            first = ahead.popleft()
            return handed(first if isinstance(first, UsvcError) else first.result())

        try:
            for item in items:
                ahead.append(item if isinstance(item, UsvcError) else pool.submit(_localize, item))
                if len(ahead) >= 2 * workers:
                    yield next_out()
            while ahead:
                yield next_out()
        except BrokenProcessPool as exc:
            raise UsvcError(f"a worker process stopped ({exc}); localize with threads instead (no --processes)") \
                from None
        finally:
            for future in ahead:  # the consumer stopped early, or a photo failed: start nothing more
                if isinstance(future, Future):
                    future.cancel()
