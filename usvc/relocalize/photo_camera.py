"""A query photo's camera, as `usvc localize` and `usvc serve` take it: --focal, --intrinsics
(fx fy cx cy), --camera (a COLMAP model and its parameters), else the EXIF focal length (unless
--no-exif), else none (the focal length estimated with the pose); with the source, named in a
failure's reason."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from usvc.core.errors import SceneError, UsvcError

if TYPE_CHECKING:
    from usvc.core.scene import Camera
    from usvc.relocalize.pose_estimate import PoseEstimate

CAMERA_PARAMS = {"SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
                 "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2",
                 "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4", "FULL_OPENCV": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6"}
HEIF_SUFFIXES = (".heic", ".heif")  # as usvc.core.images.HEIF_SUFFIXES


def is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def split_camera(tokens: list[str]) -> tuple[str, tuple[float, ...], list[str]]:
    """`--camera MODEL P1 P2 ... [PHOTO ...]` -> (model, params, photos that argparse let it swallow)."""
    model, rest = tokens[0].upper(), tokens[1:]
    if model not in CAMERA_PARAMS:
        raise UsvcError(f"--camera: unknown camera model {tokens[0]!r}; known: {', '.join(CAMERA_PARAMS)}")
    count = next((i for i, t in enumerate(rest) if not is_number(t)), len(rest))
    expected = len(CAMERA_PARAMS[model].split())
    if count != expected:
        raise UsvcError(f"--camera {model} takes {expected} parameters ({CAMERA_PARAMS[model]}), got {count}")
    return model, tuple(float(t) for t in rest[:count]), rest[count:]


class UnreadablePhoto(UsvcError):
    """A photo whose header cannot be read: its own failure, not the batch's."""


def exif_focal_source(path: Path, focal_px: float) -> str:
    """'the EXIF focal length (FocalLengthIn35mmFilm 1 mm: 4.44 px)', for the reason a query gives."""
    from PIL import Image

    from usvc.core.exif import EXIF_IFD, FOCAL_LENGTH, FOCAL_LENGTH_35MM

    tag = ""
    try:
        with Image.open(path) as img:
            exif = img.getexif()
            tags = {**exif, **exif.get_ifd(EXIF_IFD)}
        for key, label in ((FOCAL_LENGTH_35MM, "FocalLengthIn35mmFilm"), (FOCAL_LENGTH, "FocalLength")):
            if tags.get(key):
                tag = f"{label} {float(tags[key]):g} mm: "
                break
    except Exception:  # noqa: BLE001 - only for the message
        pass
    return f"the EXIF focal length ({tag}{focal_px:.4g} px)"


def photo_camera(args: argparse.Namespace, camera: tuple[str, tuple[float, ...]] | None, name: str,
                  path: Path) -> tuple[Camera | None, str, str]:
    """The first intrinsics source that applies: --focal, --intrinsics, --camera, EXIF (unless
    --no-exif), else none; with what the source is, for a failure's reason ("" for a flag). A photo
    whose header cannot be read raises UnreadablePhoto."""
    from PIL import Image

    from usvc.core.exif import exif_focal_px, oriented_size
    from usvc.core.scene import Camera

    try:
        w, h = oriented_size(path)
        focal = None if args.focal is not None or args.intrinsics is not None or camera is not None \
            or args.no_exif else exif_focal_px(path)
    except (UsvcError, OSError, ValueError, Image.DecompressionBombError) as e:
        from usvc.core.images import NO_HEIF_DECODER, heif_decoder

        if path.suffix.lower() in HEIF_SUFFIXES and not heif_decoder():
            raise UnreadablePhoto(f"cannot read image {path}: {NO_HEIF_DECODER}") from None
        raise UnreadablePhoto(str(e) if isinstance(e, UsvcError) else f"cannot read image {path} ({e})") from None
    params: tuple[float, ...]
    note = ""
    if args.focal is not None:
        flag, source, model, params = "--focal", "focal", "SIMPLE_PINHOLE", (args.focal, w / 2, h / 2)
    elif args.intrinsics is not None:
        flag, source, model, params = "--intrinsics", "intrinsics", "PINHOLE", tuple(args.intrinsics)
    elif camera is not None:
        flag, source, (model, params) = f"--camera {camera[0]}", "camera", camera
    elif focal is not None:
        flag, source, model, params = "EXIF focal length", "exif", "SIMPLE_PINHOLE", (focal, w / 2, h / 2)
        note = exif_focal_source(path, focal)
    else:
        return None, "estimated", ""
    try:
        cam = Camera(model, w, h, params)
    except SceneError as e:
        raise UsvcError(f"{flag} for {name}: {e}") from None
    cx, cy = cam.principal_point
    if not (0 < cx < w and 0 < cy < h):
        raise UsvcError(f"{flag}: principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} image {name}: "
                        "wrong image size for these intrinsics?")
    return cam, source, note


def answer_record(name: str, estimate: PoseEstimate, source: str, note: str) -> dict:
    """The record `usvc localize --format jsonl` writes for a photo (and `usvc serve` answers): its
    name, the estimate, and where its intrinsics came from (`photo_camera`'s source); a refusal
    that the EXIF focal length caused says how to do without it."""
    record = {"name": name, **estimate.to_json(), "intrinsics_source": source}
    if source == "exif" and record.get("rejected", "").startswith(note):
        record["rejected"] += "; --no-exif ignores EXIF focal lengths"
    return record
