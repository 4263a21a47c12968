"""Localize work in worker processes (`usvc serve --processes`): each spawned process holds every
served map (its own relocalizer per map, made with the arguments of the server's) and localizes
one photo at a time with `threads` threads; a request goes to a free process.

Threads share one interpreter lock, which a query's Python work holds for part of its time;
processes share nothing, so photos localized side by side do not wait for each other's Python.
The price is memory (each process holds the maps) and each process's start (Python, torch, the
maps). A photo the time limit gives up on is not left running: its process is ended and a new
one started in its place, so abandoned work never takes a core from the next request.

What a process answers is what `localize_photo` answers in the server's own process for a
relocalizer of that many threads, bit for bit: the photo's bytes travel, and the record (or the
refusal's reason and message) comes back. Processes are spawned, never forked (torch's thread
pools do not survive a fork). Messages go between the server and its own children only.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import queue
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from usvc.serve.errors import ApiError
from usvc.serve.intrinsics import PhotoIntrinsics

log = logging.getLogger("usvc.serve")

START_TIMEOUT_S = 300.0  # a process that has not loaded its maps by then is a failed start


@dataclass(frozen=True)
class WorkerMap:
    """A served map as a worker process makes it: its name, the relocalizer's class and arguments."""

    name: str
    make: Any  # the Relocalizer class (sent by name)
    args: Any  # RelocalizerArgs


def _worker_main(conn: Connection, maps: list[WorkerMap], threads: int, inline: bool) -> None:
    """A worker process: load every map, say ready, then answer one photo at a time until told to stop."""
    from usvc.relocalize.photo_batch import query_threads
    from usvc.relocalize.query_cores import inline_jobs
    from usvc.serve.photo import localize_photo

    with contextlib.ExitStack() as stack:
        stack.enter_context(query_threads(threads))
        workdir = Path(tempfile.mkdtemp(prefix="usvc-serve-worker-"))
        stack.callback(shutil.rmtree, workdir, True)
        try:
            relocalizers = {m.name: m.args.make(m.make) for m in maps}
        except Exception as e:  # a map that loaded in the server and not here: one line back
            conn.send(("failed", " ".join(str(e).split())[:300]))
            return
        conn.send(("ready", None))
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                return  # the server is gone
            if message is None:
                return
            name, data, suffix, given, photo_name = message
            try:
                with inline_jobs() if inline else contextlib.nullcontext():
                    record = localize_photo(relocalizers[name], data, suffix, given, photo_name, workdir)
                conn.send(("ok", record))
            except ApiError as err:
                conn.send(("refused", (err.reason, err.message, err.extra)))
            except Exception:
                log.exception("localize %s on map %s failed in a worker process", photo_name, name)
                conn.send(("internal", None))


class _Worker:
    """One worker process and the server's end of its pipe."""

    def __init__(self, maps: list[WorkerMap], threads: int, inline: bool) -> None:
        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(target=_worker_main, args=(child, maps, threads, inline),
                                       name="usvc-serve-worker", daemon=True)
        self.process.start()
        child.close()

    def wait_ready(self, timeout_s: float) -> None:
        if not self.conn.poll(timeout_s):
            self.stop()
            raise RuntimeError(f"a worker process did not load its maps within {timeout_s:g} s")
        try:
            kind, why = self.conn.recv()
        except (EOFError, OSError):
            kind, why = "failed", f"it stopped (exit code {self.process.exitcode})"
        if kind != "ready":
            self.stop()
            raise RuntimeError(f"a worker process could not load the maps: {why}")

    def stop(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.conn.close()
        if self.process.is_alive():
            self.process.kill()
        self.process.join(5)


class ProcessWorkers:
    """`workers` processes, each with every map of `maps`; `localize` runs a photo on a free one."""

    def __init__(self, maps: list[WorkerMap], workers: int, threads: int) -> None:
        self.maps, self.threads, self.inline = maps, threads, workers > 1
        self._free: queue.Queue[_Worker] = queue.Queue()
        self._all: list[_Worker] = []
        self._lock = threading.Lock()
        self.restarts = 0
        try:
            started = [self._new() for _ in range(workers)]  # started together, loaded side by side
            for worker in started:
                worker.wait_ready(START_TIMEOUT_S)
                self._free.put(worker)
        except BaseException:
            self.shutdown()
            raise

    def _new(self) -> _Worker:
        worker = _Worker(self.maps, self.threads, self.inline)
        with self._lock:
            self._all.append(worker)
        return worker

    def _replace(self, worker: _Worker) -> _Worker:
        """End `worker` (stuck past the time limit, or dead) and start one in its place."""
        worker.stop()
        with self._lock:
            self._all.remove(worker)
            self.restarts += 1
        fresh = self._new()
        fresh.wait_ready(START_TIMEOUT_S)
        return fresh

    def localize(self, name: str, data: bytes, suffix: str, given: PhotoIntrinsics, photo_name: str,
                 deadline: float) -> dict[str, Any]:
        """The record of the photo on a free process, by `deadline` (time.monotonic()); ApiError as
        `localize_photo` raises it, or timeout / internal."""
        worker = self._free.get()  # the work pool admits at most `workers` at a time: one is free
        try:
            try:
                worker.conn.send((name, data, suffix, given, photo_name))
                answered = worker.conn.poll(max(0.0, deadline - time.monotonic()))
                reply = worker.conn.recv() if answered else None
            except (EOFError, OSError):
                worker = self._replace(worker)
                raise ApiError("internal", "a worker process stopped on this photo (the server's log has "
                               "the details)") from None
            if reply is None:
                worker = self._replace(worker)  # the photo's work ends with its process
                raise ApiError("timeout", "no answer within the time limit of a request")
        finally:
            self._free.put(worker)
        kind, payload = reply
        if kind == "ok":
            return payload
        if kind == "refused":
            reason, message, extra = payload
            raise ApiError(reason, message, extra=extra)
        raise ApiError("internal", "the server failed on this photo (its log has the details)")

    def shutdown(self) -> None:
        with self._lock:
            workers, self._all = list(self._all), []
        for worker in workers:
            with contextlib.suppress(OSError, ValueError):
                worker.conn.send(None)
        for worker in workers:
            worker.process.join(2)
            worker.stop()
