"""What the service allows: upload size, pixels, concurrency, queue, time limits, the token."""

from __future__ import annotations

import math
from dataclasses import dataclass

from usvc.core.errors import UsvcError


@dataclass(frozen=True)
class ServeOptions:
    """Limits of `usvc serve` (the flags of the same names, docs/serve.md)."""

    max_bytes: int = 20 * 1024 * 1024  # a request body larger than this is refused (413) before it is read in full
    max_megapixels: float = 50.0  # a photo whose header claims more pixels is refused (413) before decoding
    threads: int = 1  # photos localized side by side (worker threads or processes)
    processes: bool = False  # side by side in worker processes (each holding the maps) rather than threads
    process_threads: int = 1  # with processes: the threads each process localizes a photo with
    batch: int = 1  # photos running side by side on threads that go through the network together (a GPU's); 1: off
    queue: int = 8  # requests admitted beyond those running; one more is answered 503 with Retry-After
    timeout_s: float = 30.0  # a request waiting or running longer is answered 504 (its work may finish unseen)
    body_timeout_s: float = 30.0  # the whole request body must arrive within this (a stalled upload: 408)
    retry_after_s: int = 1  # the Retry-After of a 503
    token: str | None = None  # when set, /v1/* and /metrics need `Authorization: Bearer <token>`

    def problems(self) -> list[str]:
        out = []
        if not (isinstance(self.max_bytes, int) and self.max_bytes > 0):
            out.append(f"max_bytes={self.max_bytes!r} must be a whole number > 0")
        for name in ("max_megapixels", "timeout_s", "body_timeout_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                out.append(f"{name}={value!r} must be a finite number > 0")
        if not (isinstance(self.threads, int) and self.threads >= 1):
            out.append(f"threads={self.threads!r} must be a whole number >= 1")
        if not (isinstance(self.process_threads, int) and self.process_threads >= 1):
            out.append(f"process_threads={self.process_threads!r} must be a whole number >= 1")
        if not (isinstance(self.batch, int) and self.batch >= 1):
            out.append(f"batch={self.batch!r} must be a whole number >= 1")
        elif self.batch > 1 and self.processes:
            out.append("batch > 1 needs threads, not processes (a process localizes one photo at a time)")
        if not isinstance(self.processes, bool):
            out.append(f"processes={self.processes!r} must be true or false")
        if not (isinstance(self.queue, int) and self.queue >= 0):
            out.append(f"queue={self.queue!r} must be a whole number >= 0")
        if not (isinstance(self.retry_after_s, int) and self.retry_after_s >= 1):
            out.append(f"retry_after_s={self.retry_after_s!r} must be a whole number >= 1")
        if self.token is not None and (not isinstance(self.token, str) or not self.token.strip()
                                       or any(c.isspace() for c in self.token)):
            out.append("token must be a non-empty string without spaces")
        return out

    def check(self) -> ServeOptions:
        problems = self.problems()
        if problems:
            raise UsvcError("serve options: " + "; ".join(problems))
        return self
