"""Prometheus text exposition (version 0.0.4), by hand: requests by endpoint and status, failures
by reason, the localize latency histogram, queue depth and requests running."""

from __future__ import annotations

import bisect
import threading
from collections import Counter

BUCKETS = (0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)  # seconds


class Metrics:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.requests: Counter[tuple[str, int]] = Counter()
        self.failures: Counter[str] = Counter()
        self.buckets = [0] * (len(BUCKETS) + 1)
        self.latency_sum = 0.0
        self.latency_count = 0

    def request(self, endpoint: str, status: int, reason: str | None = None) -> None:
        with self._lock:
            self.requests[(endpoint, status)] += 1
            if reason is not None and status >= 400:
                self.failures[reason] += 1

    def latency(self, seconds: float) -> None:
        with self._lock:
            self.buckets[bisect.bisect_left(BUCKETS, seconds)] += 1
            self.latency_sum += seconds
            self.latency_count += 1

    def render(self, maps: int, waiting: int, running: int, abandoned: int) -> str:
        """The text; the gauges are the work pool's (`usvc.serve.work`)."""
        with self._lock:
            lines = ["# HELP usvc_serve_requests_total HTTP requests answered, by endpoint and status.",
                     "# TYPE usvc_serve_requests_total counter"]
            lines += [f'usvc_serve_requests_total{{endpoint="{e}",status="{s}"}} {n}'
                      for (e, s), n in sorted(self.requests.items())]
            lines += ["# HELP usvc_serve_failures_total Refused or failed requests, by reason.",
                      "# TYPE usvc_serve_failures_total counter"]
            lines += [f'usvc_serve_failures_total{{reason="{r}"}} {n}' for r, n in sorted(self.failures.items())]
            lines += ["# HELP usvc_serve_localize_seconds Localize requests' time from admission to answer.",
                      "# TYPE usvc_serve_localize_seconds histogram"]
            total = 0
            for bound, n in zip((*BUCKETS, float("inf")), self.buckets):
                total += n
                le = "+Inf" if bound == float("inf") else f"{bound:g}"
                lines.append(f'usvc_serve_localize_seconds_bucket{{le="{le}"}} {total}')
            lines += [f"usvc_serve_localize_seconds_sum {self.latency_sum:.6f}",
                      f"usvc_serve_localize_seconds_count {self.latency_count}",
                      "# HELP usvc_serve_queue_depth Admitted localize requests waiting for a worker.",
                      "# TYPE usvc_serve_queue_depth gauge", f"usvc_serve_queue_depth {waiting}",
                      "# HELP usvc_serve_running Localize requests running.",
                      "# TYPE usvc_serve_running gauge", f"usvc_serve_running {running}",
                      "# HELP usvc_serve_abandoned Timed-out requests whose work still runs.",
                      "# TYPE usvc_serve_abandoned gauge", f"usvc_serve_abandoned {abandoned}",
                      "# HELP usvc_serve_maps Maps loaded.", "# TYPE usvc_serve_maps gauge",
                      f"usvc_serve_maps {maps}"]
        return "\n".join(lines) + "\n"
