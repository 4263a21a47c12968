"""The network run once for several photos: photos that threads localize side by side (a server's
requests) wait a moment for each other, and those of the same size go through the network as one
batch. On a GPU one batch of 16 costs little more than one photo; on a CPU it saves nothing
(the cores are already busy), so it is off there.

The batcher's own thread takes the oldest waiting photo, waits up to `wait_s` (or until
`max_batch` photos of its size are in), runs the network on them as one batch and hands each
photo its own coordinates; the photos' threads sleep until theirs are ready. Photos of another
size make a batch of their own; one batch runs at a time (a GPU runs them in turn anyway). What a
photo gets is the network's output for its row of the batch: a batch's products may round
differently from one photo's (another kernel), so a batched answer can differ from the unbatched
one in the last bits (the tests bound the difference).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)  # each photo is itself (the queue removes it by identity)
class _Waiting:
    gray01: np.ndarray
    done: threading.Event = field(default_factory=threading.Event)  # its coordinates (or error) are in
    coords: np.ndarray | None = None
    error: BaseException | None = None


class NetworkBatcher:
    """`batcher(gray01)` -> the photo's (h, w, 3) scene coordinates, computed with the photos of
    the same size that arrive within `wait_s` (at most `max_batch` at once) by `forward(list of
    gray01) -> list of coordinates`, on one thread of the batcher's own (started with the first
    photo; a daemon)."""

    def __init__(self, forward: Callable[[list[np.ndarray]], list[np.ndarray]], max_batch: int = 16,
                 wait_s: float = 0.003) -> None:
        if not (isinstance(max_batch, int) and max_batch >= 1):
            raise ValueError(f"max_batch={max_batch!r} must be a whole number >= 1")
        if not wait_s >= 0:
            raise ValueError(f"wait_s={wait_s!r} must be >= 0")
        self.forward, self.max_batch, self.wait_s = forward, max_batch, wait_s
        self._cond = threading.Condition()
        self._queue: list[_Waiting] = []
        self._thread: threading.Thread | None = None
        self.batches: list[int] = []  # the size of each batch run (what batching achieved)

    def __call__(self, gray01: np.ndarray) -> np.ndarray:
        me = _Waiting(gray01)
        with self._cond:
            self._queue.append(me)
            if self._thread is None:
                self._thread = threading.Thread(target=self._dispatch, name="usvc-network-batch", daemon=True)
                self._thread.start()
            self._cond.notify_all()
        me.done.wait()
        if me.error is not None:
            raise me.error
        assert me.coords is not None
        return me.coords

    def _same(self, shape: tuple[int, ...]) -> int:
        return sum(w.gray01.shape == shape for w in self._queue)

    def _dispatch(self) -> None:
        """For ever: the oldest waiting photo's size, the photos of that size that come within
        wait_s (at most max_batch), through the network together."""
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._queue))
                shape = self._queue[0].gray01.shape
                self._cond.wait_for(lambda: self._same(shape) >= self.max_batch, timeout=self.wait_s)
                batch = [w for w in self._queue if w.gray01.shape == shape][: self.max_batch]
                taken = set(map(id, batch))
                self._queue = [w for w in self._queue if id(w) not in taken]
                self.batches.append(len(batch))
            self._run(batch)

    def _run(self, batch: list[_Waiting]) -> None:
        try:
            outs = self.forward([w.gray01 for w in batch])
            for w, out in zip(batch, outs):
                w.coords = out
        except BaseException as e:  # each photo of the batch gets the error
            for w in batch:
                w.error = e
        finally:
            for w in batch:
                w.done.set()
