"""A localize request's body, read under the limits (bytes, time) and taken apart: the photo's
bytes, its intrinsics and its name, from multipart/form-data, JSON with base64, or a bare image
body with the intrinsics as query parameters."""

from __future__ import annotations

import asyncio
import base64
import binascii
import json
from dataclasses import dataclass
from typing import Any

from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException
from starlette.requests import Request

from usvc.serve.errors import ApiError
from usvc.serve.intrinsics import MAX_NAME, PhotoIntrinsics, parse_intrinsics

FIELDS = ("photo", "name", "focal", "intrinsics", "camera", "no_exif")
DEFAULT_NAME = "photo"


@dataclass(frozen=True)
class LocalizeRequest:
    photo: bytes
    intrinsics: PhotoIntrinsics
    name: str


async def read_body(request: Request, max_bytes: int, timeout_s: float) -> bytes:
    """The whole body, refused (413) past `max_bytes` (from Content-Length before reading any), and
    (408) when it has not all arrived within `timeout_s`: a client that stalls holds no worker."""
    length = request.headers.get("content-length")
    if length is not None:
        if not length.strip().isdigit():
            raise ApiError("bad_request", f"Content-Length {length[:20]!r} is not a number")
        if int(length) > max_bytes:
            raise ApiError("too_large", f"the request is {int(length)} bytes, more than the {max_bytes} allowed")
    chunks: list[bytes] = []
    size = 0

    async def collect() -> None:
        nonlocal size
        async for chunk in request.stream():
            size += len(chunk)
            if size > max_bytes:
                raise ApiError("too_large", f"the request is more than the {max_bytes} bytes allowed")
            chunks.append(chunk)

    try:
        await asyncio.wait_for(collect(), timeout_s)
    except asyncio.TimeoutError:
        raise ApiError("body_timeout", f"the request body did not arrive within {timeout_s:g} s") from None
    return b"".join(chunks)


def _name(value: Any) -> str:
    if value is None or value == "":
        return DEFAULT_NAME
    if not isinstance(value, str):
        raise ApiError("bad_request", f"name must be a string, got {type(value).__name__}")
    if len(value) > MAX_NAME or any(ord(c) < 32 or ord(c) == 127 for c in value):
        raise ApiError("bad_request", f"name must be at most {MAX_NAME} printable characters")
    return value


def _base64(value: Any) -> bytes:
    if not isinstance(value, str):
        raise ApiError("bad_request", f"photo must be a base64 string, got {type(value).__name__}")
    if value.startswith("data:") and "," in value:  # a data: URL as a browser makes it
        value = value.split(",", 1)[1]
    try:
        return base64.b64decode("".join(value.split()), validate=True)
    except (binascii.Error, ValueError):
        raise ApiError("bad_request", "photo is not valid base64") from None


def _unknown(fields: dict[str, Any]) -> None:
    extra = sorted(set(fields) - set(FIELDS))
    if extra:
        raise ApiError("bad_request", f"unknown field(s) {', '.join(repr(e[:30]) for e in extra[:5])}; "
                       f"known: {', '.join(FIELDS)}")


async def parse(request: Request, body: bytes, max_bytes: int) -> LocalizeRequest:
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == "multipart/form-data":
        async def replay() -> dict[str, Any]:
            return {"type": "http.request", "body": body, "more_body": False}

        try:
            form = await Request(request.scope, replay).form(max_files=1, max_fields=len(FIELDS),
                                                            max_part_size=max_bytes)
        except HTTPException as e:
            raise ApiError("bad_request", f"the multipart body cannot be read ({e.detail})") from None
        except Exception as e:  # noqa: BLE001 - a malformed body of any kind is the client's
            raise ApiError("bad_request", f"the multipart body cannot be read ({type(e).__name__})") from None
        try:
            fields = {k: v for k, v in form.multi_items()}
            _unknown(fields)
            photo = fields.get("photo")
            if not isinstance(photo, UploadFile):
                raise ApiError("bad_request", "multipart: the photo goes in a file field named 'photo'")
            data = await photo.read()
            texts = {k: v for k, v in fields.items() if k != "photo"}
            if any(not isinstance(v, str) for v in texts.values()):
                raise ApiError("bad_request", "multipart: only 'photo' is a file; the other fields are text")
            name = texts.get("name") or (photo.filename or "").replace("\\", "/").rsplit("/", 1)[-1] or None
            return LocalizeRequest(data, parse_intrinsics(texts), _name(name))
        finally:
            await form.close()
    if kind == "application/json":
        try:
            fields = json.loads(body)
        except (ValueError, RecursionError) as e:
            raise ApiError("bad_json", f"the body is not JSON ({' '.join(str(e).split())[:100]})") from None
        if not isinstance(fields, dict):
            raise ApiError("bad_json", f"the body must be a JSON object, got {type(fields).__name__}")
        _unknown(fields)
        if "photo" not in fields:
            raise ApiError("bad_request", "JSON: the photo goes in 'photo', base64")
        return LocalizeRequest(_base64(fields["photo"]), parse_intrinsics(fields), _name(fields.get("name")))
    if kind.startswith("image/") or kind == "application/octet-stream":
        fields = dict(request.query_params)
        _unknown(fields)
        if "photo" in fields:
            raise ApiError("bad_request", "a bare image body is the photo: no 'photo' query parameter")
        return LocalizeRequest(body, parse_intrinsics(fields), _name(fields.get("name")))
    raise ApiError("unsupported_media_type", f"Content-Type {kind[:60] or '(none)'!r}: send multipart/form-data "
                   "(a file field 'photo'), application/json (base64 'photo') or the image itself (image/*)")
