"""A request's intrinsics, read as `usvc localize` reads its flags (focal, fx fy cx cy, a COLMAP
camera model, else EXIF unless no_exif, else estimated with the pose).

The camera of each photo and its source come from `usvc.relocalize.photo_camera`, as for
`usvc localize`.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from usvc.core.errors import UsvcError
from usvc.relocalize.photo_camera import CAMERA_PARAMS, UnreadablePhoto, photo_camera, split_camera
from usvc.serve.errors import ApiError

if TYPE_CHECKING:
    from usvc.core.scene import Camera

__all__ = ["CAMERA_PARAMS", "PhotoIntrinsics", "UnreadablePhoto", "camera_of", "parse_intrinsics"]

FIELDS = ("focal", "intrinsics", "camera")
MAX_NAME = 200


@dataclass(frozen=True)
class PhotoIntrinsics:
    """What a request says of its photo's camera (at most one of focal, intrinsics, camera)."""

    focal: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    camera: tuple[str, tuple[float, ...]] | None = None
    no_exif: bool = False


def _number(field: str, value: Any) -> float:
    """A finite number from JSON (int or float, not bool) or from a form's text."""
    if isinstance(value, str):
        try:
            value = float(value.strip())
        except ValueError:
            raise ApiError("bad_intrinsics", f"{field}: {value[:40]!r} is not a number") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ApiError("bad_intrinsics", f"{field} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ApiError("bad_intrinsics", f"{field} must be finite, got {value}")
    return value


def _numbers(field: str, value: Any) -> list[float]:
    """A list of numbers from JSON, or from a form's text (separated by spaces or commas)."""
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    if not isinstance(value, list):
        raise ApiError("bad_intrinsics", f"{field} must be a list of numbers, got {type(value).__name__}")
    return [_number(f"{field}[{i}]", v) for i, v in enumerate(value[:64])]


def _flag(field: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ("1", "true", "yes", "on", "0", "false", "no", "off", ""):
        return value.strip().lower() in ("1", "true", "yes", "on")
    raise ApiError("bad_request", f"{field} must be true or false, got {str(value)[:40]!r}")


def parse_intrinsics(fields: dict[str, Any]) -> PhotoIntrinsics:
    """The intrinsics of a request's fields (JSON values, or a form's strings). `camera` is
    {"model": M, "params": [...]} or the text "MODEL p1 p2 ..." (COLMAP order, as --camera)."""
    given = [f for f in FIELDS if fields.get(f) not in (None, "")]
    if len(given) > 1:
        raise ApiError("bad_intrinsics", f"give at most one of focal, intrinsics, camera (got {', '.join(given)})")
    no_exif = _flag("no_exif", fields.get("no_exif", False))
    if not given:
        return PhotoIntrinsics(no_exif=no_exif)
    field, value = given[0], fields[given[0]]
    if field == "focal":
        focal = _number("focal", value)
        if focal <= 0:
            raise ApiError("bad_intrinsics", f"focal must be > 0 (pixels of the photo as shown), got {focal:g}")
        return PhotoIntrinsics(focal=focal, no_exif=no_exif)
    if field == "intrinsics":
        values = _numbers("intrinsics", value)
        if len(values) != 4:
            raise ApiError("bad_intrinsics", f"intrinsics are fx fy cx cy (4 numbers), got {len(values)}")
        fx, fy, cx, cy = values
        return PhotoIntrinsics(intrinsics=(fx, fy, cx, cy), no_exif=no_exif)
    if isinstance(value, dict):
        model, params = value.get("model"), value.get("params")
        if not isinstance(model, str):
            raise ApiError("bad_intrinsics", "camera.model must be a COLMAP camera model name, e.g. OPENCV")
        tokens = [model, *(repr(v) for v in _numbers("camera.params", params))]
    elif isinstance(value, str):
        tokens = value.replace(",", " ").split()
        for i, t in enumerate(tokens[1:]):
            _number(f"camera parameter {i + 1}", t)
    else:
        raise ApiError("bad_intrinsics", f"camera must be {{\"model\": ..., \"params\": [...]}} or text "
                       f"\"MODEL p1 p2 ...\", got {type(value).__name__}")
    if not tokens:
        raise ApiError("bad_intrinsics", "camera names no model")
    try:
        model, params, rest = split_camera(tokens)
    except UsvcError as err:
        raise ApiError("bad_intrinsics", str(err).replace("--camera", "camera")) from None
    if rest:
        raise ApiError("bad_intrinsics", f"camera {model}: {len(rest)} values too many")
    return PhotoIntrinsics(camera=(model, params), no_exif=no_exif)


def camera_of(given: PhotoIntrinsics, name: str, path: Path) -> tuple[Camera | None, str, str]:
    """(camera or None, source, note) of the photo at `path`, exactly as `usvc localize` finds
    them (`photo_camera`): the source goes into the record, the note into a refusal's reason.
    Raises UnreadablePhoto (the header) or UsvcError (the intrinsics against the photo's size)."""
    args = argparse.Namespace(focal=given.focal, intrinsics=list(given.intrinsics) if given.intrinsics else None,
                              no_exif=given.no_exif)
    return photo_camera(args, given.camera, name, path)


def plain(message: str) -> str:
    """A message of photo_camera without the CLI's flag names."""
    for flag in ("--focal", "--intrinsics", "--camera", "--no-exif"):
        message = message.replace(flag, flag[2:].replace("-", "_"))
    return message
