"""Every refused request is one JSON object: {"error": one line, "reason": a stable code,
"status": the HTTP status}, never a traceback."""

from __future__ import annotations

from typing import Any

# reason -> HTTP status (docs/serve.md's table)
REASONS = {
    "bad_request": 400, "bad_photo": 400, "bad_intrinsics": 400, "bad_json": 400,
    "unauthorized": 401, "not_found": 404, "unknown_map": 404, "method_not_allowed": 405,
    "body_timeout": 408, "too_large": 413, "too_many_pixels": 413, "unsupported_media_type": 415,
    "pose_refused": 422, "internal": 500, "busy": 503, "timeout": 504,
}


class ApiError(Exception):
    """A request the service refuses: `reason` (a key of REASONS) gives the status."""

    def __init__(self, reason: str, message: str, headers: dict[str, str] | None = None,
                 extra: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.status = REASONS[reason]
        self.message = " ".join(str(message).split())  # one line
        self.headers = headers or {}
        self.extra = extra or {}

    def body(self) -> dict[str, Any]:
        return {"error": self.message, "reason": self.reason, "status": self.status, **self.extra}


def status_reason(status: int) -> str:
    """The reason code of an HTTP status raised by the framework itself (404 route, 405, ...)."""
    return {404: "not_found", 405: "method_not_allowed", 413: "too_large", 415: "unsupported_media_type",
            401: "unauthorized"}.get(status, "bad_request" if 400 <= status < 500 else "internal")
