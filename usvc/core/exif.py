"""Photos as a camera took them: EXIF orientation and the focal length in pixels from EXIF, read
from the header (opened under the MAX_IMAGE_PIXELS limit) without decoding the pixels.

Every size and focal length here is for the image as decoded *after* its EXIF orientation is
applied (a portrait photo stored as landscape pixels with orientation 6 is portrait), which is
how viewers show it and how :func:`usvc.core.images.read_image_bgr` decodes it.
"""

from __future__ import annotations

import math
import struct
import threading
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

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
SWAPS_AXES = (5, 6, 7, 8)
# Larger images are refused from their header, before anything is decoded: no camera makes more
# pixels in one shot (phone sensors reach 200 MP, medium format 150 MP), and a tiny file can claim
# billions (a "decompression bomb"). Up to it, usvc.core.images decodes a photo in full up to
# MAX_DECODE_PIXELS and a larger JPEG reduced, by the JPEG decoder's own scaling.
MAX_IMAGE_PIXELS = 250_000_000
_PIL_LIMIT_LOCK = threading.Lock()


def _header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the header of an image Pillow refused as a decompression bomb."""
    with _PIL_LIMIT_LOCK:
        limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with warnings.catch_warnings(), Image.open(path) as img:
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                return img.size
        except Exception:  # noqa: BLE001 - only for the message
            return None
        finally:
            Image.MAX_IMAGE_PIXELS = limit


def _too_large(path: Path, size: tuple[int, int] | None) -> SceneError:
    claim = f"is {size[0]}x{size[1]} = {size[0] * size[1] / 1e6:.0f} megapixels" if size else "claims more pixels"
    return SceneError(f"image {path} {claim}, more than any camera makes (the {MAX_IMAGE_PIXELS / 1e6:.0f} "
                      "megapixel limit, usvc.core.exif.MAX_IMAGE_PIXELS): downscale it, or is its header corrupt?")


def open_checked(path: str | Path) -> Image.Image:
    """Pillow's lazy open (the header only) with the size limit applied; Pillow's own decoding
    errors pass through."""
    try:
        with _PIL_LIMIT_LOCK, warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our limit applies instead
            limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, max(MAX_IMAGE_PIXELS, Image.MAX_IMAGE_PIXELS or 0)
            try:
                img = Image.open(path)  # the header only: nothing is decoded here
            finally:
                Image.MAX_IMAGE_PIXELS = limit
    except Image.DecompressionBombError:
        raise _too_large(Path(path), _header_size(Path(path))) from None
    w, h = img.size
    if w * h > MAX_IMAGE_PIXELS:
        img.close()
        raise _too_large(Path(path), (w, h))
    return img


def _open(path: str | Path) -> Image.Image:
    try:
        return open_checked(path)
    except FileNotFoundError:
        raise SceneError(f"image not found: {path}") from None
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise SceneError(f"cannot decode image {path} ({e})") from None


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Chunks whose content Pillow's Image.getexif reads (EXIF, and EXIF or XMP inside text chunks).
_PNG_METADATA_CHUNKS = (b"eXIf", b"tEXt", b"zTXt", b"iTXt")


def png_metadata_after_pixels(path: str | Path) -> bool:
    """Whether a PNG file holds a metadata chunk after its first pixel chunk (IDAT), walking the
    chunk headers only; True too when the file does not read as a PNG's chunks to its end."""
    try:
        with open(path, "rb") as f:
            if f.read(8) != PNG_SIGNATURE:
                return True
            seen_pixels = False
            while True:
                head = f.read(8)
                if len(head) < 8:
                    return True  # no IEND: truncated
                length, kind = struct.unpack(">I4s", head)
                if kind == b"IEND":
                    return False
                if kind == b"IDAT":
                    seen_pixels = True
                elif seen_pixels and kind in _PNG_METADATA_CHUNKS:
                    return True
                f.seek(length + 4, 1)  # the data and its CRC
    except OSError:
        return True


def read_exif(img: Image.Image) -> Image.Exif | None:
    """The image's EXIF block, or None when it has none or it is malformed.

    Pillow finds a PNG's EXIF only by decoding the whole image (its metadata may follow the
    pixels); when the file has no metadata after its pixels, the chunks read with the header
    already hold all of it, and it is read from them without decoding (the same block).
    """
    # A malformed EXIF block must not make a decodable photo unusable: Pillow raises a zoo of
    # exception types (struct.error, SyntaxError, ...) for it, so treat any of them as "no EXIF".
    try:
        if (img.format == "PNG" and "exif" not in img.info and isinstance(getattr(img, "filename", None), str)
                and img.filename and not png_metadata_after_pixels(img.filename)):
            return Image.Image.getexif(img)
        return img.getexif()
    except Exception:
        return None


def orientation_of(exif: Image.Exif | None) -> int:
    """The orientation tag of an EXIF block (1-8; 1 when absent or invalid)."""
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


def stored_size(img: Image.Image) -> tuple[int, int]:
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
            return orientation_of(read_exif(img))
    except Exception:  # noqa: BLE001 - a hint for an error message, never an error of its own
        return 1


def oriented_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of the photo with its EXIF orientation applied, from the header only."""
    with _open(path) as img:
        w, h = stored_size(img)
        return (h, w) if orientation_of(read_exif(img)) in SWAPS_AXES else (w, h)


def exif_focal_px(path: str | Path) -> float | None:
    """Focal length in pixels of the oriented photo from its EXIF, or None when unknown.

    FocalLengthIn35mmFilm first: f_px = f35 / 36 mm * max(W, H), taking 35 mm film as 36 mm on
    its long side (COLMAP divides by 35; the CIPA definition, by the diagonal, agrees for 3:2
    sensors). Otherwise FocalLength (mm) times FocalPlaneXResolution (sensor pixels per unit)
    gives pixels of the full-resolution image (PixelX/YDimension), scaled to this image's size.
    """
    with _open(path) as img:
        w, h = stored_size(img)
        exif = read_exif(img)
    if exif is None:
        return None
    try:
        tags = {**exif, **exif.get_ifd(EXIF_IFD)}  # some writers put Exif tags in IFD0
    except Exception:  # malformed Exif IFD: see read_exif
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


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels as stored -> pixels as shown, for an EXIF orientation 1..8."""
    ops = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: np.rot90(a, -1)[::-1],
           8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[orientation](image))
