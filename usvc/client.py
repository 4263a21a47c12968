"""A small client of `usvc serve` (docs/serve.md), on httpx (`pip install httpx`, or the
`client` extra):

    from usvc.client import Client
    with Client("http://127.0.0.1:8000", token="...") as c:
        c.maps()                                    # [{"name": "office", ...}]
        record = c.localize("office", "a.jpg", focal=1450.0)
        record["q_wxyz"], record["t"], record["camera_center"]

A refused request raises ServeError (its status, reason, one-line message and, for a refused
pose, the record); 503 answers are retried after their Retry-After, `retries` times.
"""

from __future__ import annotations

import time
from urllib.parse import quote
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from usvc.core.errors import UsvcError


class ServeError(UsvcError):
    """A request the server refused: `status`, `reason` (docs/serve.md's table), `record` for 422."""

    def __init__(self, status: int, reason: str, message: str, record: dict | None = None,
                 retry_after: float | None = None) -> None:
        super().__init__(f"HTTP {status} {reason}: {message}")
        self.status, self.reason, self.message, self.record, self.retry_after = (status, reason, message, record,
                                                                                  retry_after)


def _httpx() -> Any:
    try:
        import httpx
    except ImportError:
        raise UsvcError("usvc.client needs httpx: pip install httpx (or usvc[client])") from None
    return httpx


class Client:
    """`base_url` of a server; `token` its bearer token; `http` an httpx.Client to use instead of
    a new one (FastAPI's TestClient is one)."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 60.0,
                 retries: int = 2, http: Any = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._own = http is None
        self.http = http if http is not None else _httpx().Client(base_url=base_url, timeout=timeout)
        self.headers, self.retries = headers, retries

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._own:
            self.http.close()

    def _request(self, method: str, url: str, **kwargs: Any) -> Any:
        for attempt in range(self.retries + 1):
            r = self.http.request(method, url, headers=self.headers, **kwargs)
            if r.status_code < 400:
                return r
            try:
                body = r.json()
            except ValueError:
                body = {}
            if not isinstance(body, dict):
                body = {}
            retry = r.headers.get("retry-after")
            err = ServeError(r.status_code, str(body.get("reason", "http_error")),
                             str(body.get("error", r.text[:200])), body.get("record"),
                             float(retry) if retry and retry.isdigit() else None)
            if r.status_code != 503 or attempt == self.retries:
                raise err
            time.sleep(err.retry_after or 1.0)
        raise AssertionError("unreachable")

    def health(self) -> dict[str, Any]:
        return self._request("GET", "/healthz").json()

    def maps(self) -> list[dict[str, Any]]:
        return self._request("GET", "/v1/maps").json()["maps"]

    def localize(self, map_name: str, photo: str | Path | bytes, *, focal: float | None = None,
                 intrinsics: Sequence[float] | None = None, camera: str | None = None, no_exif: bool = False,
                 name: str | None = None) -> dict[str, Any]:
        """The record of `usvc localize` for the photo (a path or the file's bytes); ServeError for
        a refusal (422: a refused pose, its record in `.record`)."""
        if isinstance(photo, (str, Path)):
            name = name or Path(photo).name
            photo = Path(photo).read_bytes()
        fields: dict[str, str] = {}
        if focal is not None:
            fields["focal"] = repr(float(focal))
        if intrinsics is not None:
            fields["intrinsics"] = " ".join(repr(float(v)) for v in intrinsics)
        if camera is not None:
            fields["camera"] = camera
        if no_exif:
            fields["no_exif"] = "true"
        if name:
            fields["name"] = name
        files = {"photo": (name or "photo", photo, "application/octet-stream")}
        return self._request("POST", f"/v1/maps/{quote(str(map_name), safe='')}/localize", files=files, data=fields).json()
