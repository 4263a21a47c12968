"""Guards of an all-or-nothing change to a checkout: an exclusive lock held while it is made, and
signals (SIGTERM, SIGHUP) turned into KeyboardInterrupt so that every interruption is undone alike."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

from usvc.core.errors import UsvcError

log = logging.getLogger(__name__)


@contextlib.contextmanager
def checkout_lock(checkout: Path, lock_file: str) -> Iterator[None]:
    """An exclusive flock on ``<checkout>/<lock_file>`` (released by the kernel even if the process
    is killed); a second `usvc map` waits for it. The file is removed on release."""
    path = checkout / lock_file
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise UsvcError(f"cannot create the lock {path} ({e.strerror})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                log.info("another `usvc map` is adding a scene to %s: waiting for it", checkout)
                fcntl.flock(fd, fcntl.LOCK_EX)
            try:  # the holder before us may have removed the file: then lock the new one
                current = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
        except BaseException:
            os.close(fd)
            raise
        if current:
            break
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


class SignalGuard:
    """While registering: SIGTERM and SIGHUP raise KeyboardInterrupt like Ctrl-C does, so they are
    undone the same way; once undoing (``disarm``), further signals are only noted, so that a second
    Ctrl-C cannot leave the undo half done. A no-op off the main thread (signals go to it only)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.armed = True
        self.old: dict[int, object] = {}

    def _handle(self, signum: int, frame: object) -> None:
        if self.armed:
            self.armed = False
            raise KeyboardInterrupt(signal.Signals(signum).name)
        log.warning("%s while undoing: finishing the undo first", signal.Signals(signum).name)

    def disarm(self) -> None:
        self.armed = False

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                if signal.getsignal(s) is not signal.SIG_IGN:  # an ignored signal (nohup) stays ignored
                    self.old[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for s, old in self.old.items():
            signal.signal(s, old if old is not None else signal.SIG_DFL)
