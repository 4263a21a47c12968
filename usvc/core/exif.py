"""Photos as a camera took them: EXIF orientation and the focal length in pixels from EXIF.

Every size and focal length here is for the image as decoded *after* its EXIF orientation is
applied (a portrait photo stored as landscape pixels with orientation 6 is portrait), which is
how viewers show it and how :func:`read_image_bgr` decodes it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from usvc.core.errors import SceneError

ORIENTATION = 0x0112
EXIF_IFD = 0x8769
FOCAL_LENGTH = 0x920A  # mm
FOCAL_LENGTH_35MM = 0xA405  # mm, 35 mm film equivalent; 0 = unknown
FOCAL_PLANE_X_RESOLUTION = 0xA20E  # sensor pixels per FocalPlaneResolutionUnit
FOCAL_PLANE_RESOLUTION_UNIT = 0xA210
PIXEL_X_DIMENSION, PIXEL_Y_DIMENSION = 0xA002, 0xA003  # the size the sensor resolution refers to
FILM_LONG_SIDE_MM = 36.0  # 35 mm film (full frame) is 36 x 24 mm
# FocalPlaneResolutionUnit -> millimetres; 2 (inch) is EXIF's default; 4 and 5 are TIFF/EP's.
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}
_SWAPS_AXES = (5, 6, 7, 8)


def _open(path: str | Path) -> Image.Image:
    try:
        return Image.open(path)
    except FileNotFoundError:
        raise SceneError(f"image not found: {path}") from None
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise SceneError(f"cannot decode image {path} ({e})") from None


def _exif(img: Image.Image) -> Image.Exif | None:
    # A malformed EXIF block must not make a decodable photo unusable: Pillow raises a zoo of
    # exception types (struct.error, SyntaxError, ...) for it, so treat any of them as "no EXIF".
    try:
        return img.getexif()
    except Exception:
        return None


def _orientation(exif: Image.Exif | None) -> int:
    value = exif.get(ORIENTATION, 1) if exif is not None else 1
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def _number(value: object) -> float | None:
    """A finite positive number from an EXIF value (rationals included), else None."""
    if isinstance(value, tuple) and len(value) == 2:  # a raw (numerator, denominator) pair
        value = value[0] / value[1] if value[1] else math.nan
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def _stored_size(img: Image.Image) -> tuple[int, int]:
    """(width, height) of the pixels as stored; Pillow >= 11 reports a TIFF's size already oriented."""
    if img.format == "TIFF":
        tags = getattr(img, "tag_v2", {})
        if isinstance(tags.get(256), int) and isinstance(tags.get(257), int):
            return tags[256], tags[257]
    return img.size


def exif_orientation(path: str | Path) -> int:
    """The photo's EXIF orientation tag (1-8; 1 when absent or unreadable)."""
    try:
        with _open(path) as img:
            return _orientation(_exif(img))
    except Exception:  # noqa: BLE001 - a hint for an error message, never an error of its own
        return 1


def oriented_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of the photo with its EXIF orientation applied, from the header only."""
    with _open(path) as img:
        w, h = _stored_size(img)
        return (h, w) if _orientation(_exif(img)) in _SWAPS_AXES else (w, h)


def exif_focal_px(path: str | Path) -> float | None:
    """Focal length in pixels of the oriented photo from its EXIF, or None when unknown.

    FocalLengthIn35mmFilm first: f_px = f35 / 36 mm * max(W, H), taking 35 mm film as 36 mm on
    its long side (COLMAP divides by 35; the CIPA definition, by the diagonal, agrees for 3:2
    sensors). Otherwise FocalLength (mm) times FocalPlaneXResolution (sensor pixels per unit)
    gives pixels of the full-resolution image (PixelX/YDimension), scaled to this image's size.
    """
    with _open(path) as img:
        w, h = _stored_size(img)
        exif = _exif(img)
    if exif is None:
        return None
    try:
        tags = {**exif, **exif.get_ifd(EXIF_IFD)}  # some writers put Exif tags in IFD0
    except Exception:  # malformed Exif IFD: see _exif
        tags = dict(exif)
    long_side = max(w, h)
    f35 = _number(tags.get(FOCAL_LENGTH_35MM))
    if f35 is not None:
        return f35 / FILM_LONG_SIDE_MM * long_side
    f_mm = _number(tags.get(FOCAL_LENGTH))
    density = _number(tags.get(FOCAL_PLANE_X_RESOLUTION))
    unit = tags.get(FOCAL_PLANE_RESOLUTION_UNIT, 2)
    if f_mm is None or density is None or unit not in _UNIT_MM:
        return None
    f_px = f_mm * density / _UNIT_MM[unit]
    full_w, full_h = _number(tags.get(PIXEL_X_DIMENSION)), _number(tags.get(PIXEL_Y_DIMENSION))
    if full_w is not None and full_h is not None:
        f_px *= long_side / max(full_w, full_h)
    return f_px if math.isfinite(f_px) and f_px > 0 else None


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV logs decoder failures to stderr itself; the caller reports them in one line."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels as stored -> pixels as shown, for an EXIF orientation 1..8."""
    ops = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: np.rot90(a, -1)[::-1],
           8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[orientation](image))


def jpeg_is_complete(data: bytes) -> bool:
    """Whether a JPEG stream reaches its end-of-image marker (decoders fill a truncated file with
    grey without failing). Walks the marker segments and entropy-coded scans; bytes after the end
    marker (phones append motion-photo video there) are not looked at."""
    if data[:2] != b"\xff\xd8":
        return True  # not a JPEG stream: nothing to say
    pos, n = 2, len(data)
    while pos < n:
        if data[pos] != 0xFF:
            return False  # lost sync: a corrupt stream
        while pos < n and data[pos] == 0xFF:  # fill bytes
            pos += 1
        if pos >= n:
            return False
        marker = data[pos]
        pos += 1
        if marker == 0xD9:
            return True
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:
            continue
        if pos + 2 > n:
            return False
        pos += (data[pos] << 8) | data[pos + 1]
        if marker == 0xDA:  # entropy-coded data up to the next marker that is not a stuffed 0xFF00 or RST
            while True:
                pos = data.find(b"\xff", pos)
                if pos < 0 or pos + 1 >= n:
                    return False
                nxt = data[pos + 1]
                if nxt == 0x00 or 0xD0 <= nxt <= 0xD7:
                    pos += 2
                    continue
                break
    return False


def read_image_bgr(path: str | Path) -> np.ndarray:
    """uint8 HxWx3 BGR pixels with the EXIF orientation applied (the size oriented_size gives).

    OpenCV decodes, with its own orientation handling off so that every format is turned by the
    same rule. Pillow decodes TIFFs (OpenCV turns them whatever it is told, and OpenCV 5 fails on
    orientations 5-8) and whatever OpenCV cannot.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"image not found: {path}")
    try:
        with Image.open(path) as img:
            orientation, fmt = _orientation(_exif(img)), img.format
    except (OSError, UnidentifiedImageError, ValueError):
        orientation, fmt = 1, None  # OpenCV may still decode it
    if fmt == "JPEG" and not jpeg_is_complete(path.read_bytes()):
        raise SceneError(f"cannot decode image {path}: truncated or corrupt JPEG (no end-of-image marker)")
    if fmt != "TIFF":
        with _quiet_opencv():
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if bgr is not None:
            return apply_orientation(bgr, orientation)
    try:
        with Image.open(path) as img:
            img.load()  # Pillow >= 11 turns a TIFF while loading it and then drops its orientation tag
            rgb = np.asarray(ImageOps.exif_transpose(img).convert("RGB"))
    except (OSError, UnidentifiedImageError, ValueError):
        raise SceneError(f"cannot decode image {path}") from None
    return np.ascontiguousarray(rgb[..., ::-1])
