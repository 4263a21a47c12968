"""Photos as a camera took them: EXIF orientation and the focal length in pixels from EXIF.

Every size and focal length here is for the image as decoded *after* its EXIF orientation is
applied (a portrait photo stored as landscape pixels with orientation 6 is portrait), which is
how viewers show it and how :func:`read_image_bgr` decodes it.
"""

from __future__ import annotations

import contextlib
import math
import threading
import warnings
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
# Larger images are refused from their header, before anything is decoded: 100 MP is 300 MB of
# 8-bit BGR (a 12000x8000 medium-format photo is 96 MP), and a tiny file can claim billions
# (a "decompression bomb"). Pillow's own check warns above 89 MP and raises above 179 MP.
MAX_IMAGE_PIXELS = 100_000_000
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
    return SceneError(f"image {path} {claim}, more than the {MAX_IMAGE_PIXELS / 1e6:.0f} megapixel limit "
                      f"(usvc.core.exif.MAX_IMAGE_PIXELS): downscale it, or is its header corrupt?")


def _open_checked(path: str | Path) -> Image.Image:
    """Pillow's lazy open (the header only) with the size limit applied; Pillow's own decoding
    errors pass through."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our limit applies instead
            img = Image.open(path)
    except Image.DecompressionBombError:
        raise _too_large(Path(path), _header_size(Path(path))) from None
    w, h = img.size
    if w * h > MAX_IMAGE_PIXELS:
        img.close()
        raise _too_large(Path(path), (w, h))
    return img


def _open(path: str | Path) -> Image.Image:
    try:
        return _open_checked(path)
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


# Pillow modes of samples wider than 8 bits: Pillow's convert("RGB") clips them (16-bit -> all
# white, floats in 0..1 -> all black), so read_image_bgr scales them itself.
_WIDE_MODES = frozenset({"I;16", "I;16B", "I;16L", "I;16N", "I;16S", "I", "F"})
FLOAT_RANGE_TOLERANCE = 1e-3  # float pixels are read as 0..1; a little overshoot (resampling ringing) is clipped


def to_uint8(pixels: np.ndarray, where: str | Path) -> np.ndarray:
    """8-bit samples from a decoder's array: 16-bit / 257 (rounded), floats in 0..1 * 255
    (rounded, clipped); other sample types are refused by name."""
    if pixels.dtype == np.uint8:
        return pixels
    if pixels.dtype == np.uint16:
        return ((pixels.astype(np.uint32) + 128) // 257).astype(np.uint8)
    if pixels.dtype.kind == "f":
        if not np.isfinite(pixels).all():
            raise SceneError(f"image {where}: {pixels.dtype} pixels include NaN or infinity: save it as 8 or 16 bits")
        lo, hi = float(pixels.min()), float(pixels.max())
        if lo < -FLOAT_RANGE_TOLERANCE or hi > 1 + FLOAT_RANGE_TOLERANCE:
            raise SceneError(f"image {where}: {pixels.dtype} pixels range {lo:g}..{hi:g}, but floating-point photos "
                             "are read as 0..1 (HDR or data, not a photo?): save it as 8 or 16 bits")
        return np.rint(np.clip(pixels, 0.0, 1.0) * 255.0).astype(np.uint8)
    raise SceneError(f"image {where}: {pixels.dtype} samples ({8 * pixels.dtype.itemsize}-bit "
                     f"{'integer' if pixels.dtype.kind in 'iu' else pixels.dtype.kind}) are not supported: "
                     "save it as 8 or 16 bits")


def _to_bgr(pixels: np.ndarray, rgb: bool) -> np.ndarray:
    """uint8 HxWx3 BGR from gray, gray+alpha, RGB(A) (``rgb``) or BGR(A) samples."""
    if pixels.ndim == 3 and pixels.shape[2] == 1:
        pixels = pixels[..., 0]
    if pixels.ndim == 2:
        return np.ascontiguousarray(np.repeat(pixels[..., None], 3, axis=2))
    if pixels.shape[2] == 2:  # gray + alpha
        return np.ascontiguousarray(np.repeat(pixels[..., :1], 3, axis=2))
    colour = pixels[..., :3]
    return np.ascontiguousarray(colour[..., ::-1] if rgb else colour)


def read_image_bgr(path: str | Path) -> np.ndarray:
    """uint8 HxWx3 BGR pixels with the EXIF orientation applied (the size oriented_size gives).

    OpenCV decodes, with its own orientation handling off so that every format is turned by the
    same rule. Pillow decodes TIFFs (OpenCV turns them whatever it is told, and OpenCV 5 fails on
    orientations 5-8) and whatever OpenCV cannot. Images over MAX_IMAGE_PIXELS are refused from
    their header; 16-bit samples are scaled to 8 bits (/257) and floating-point ones in 0..1 by 255.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"image not found: {path}")
    try:
        with _open_checked(path) as img:
            orientation, fmt = _orientation(_exif(img)), img.format
    except (OSError, UnidentifiedImageError, ValueError):
        orientation, fmt = 1, None  # OpenCV may still decode it
    if fmt == "JPEG" and not jpeg_is_complete(path.read_bytes()):
        raise SceneError(f"cannot decode image {path}: truncated or corrupt JPEG (no end-of-image marker)")
    if fmt != "TIFF":
        with _quiet_opencv():
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            if bgr is None and fmt is None:  # e.g. an RGB float TIFF, which only IMREAD_UNCHANGED reads
                raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
                if raw is not None and raw.size:
                    return _to_bgr(to_uint8(raw, path), rgb=False)
        if bgr is not None:
            return apply_orientation(bgr, orientation)
    try:
        with Image.open(path) as img:  # its size passed _open_checked (or Pillow cannot read it)
            stored = _stored_size(img)
            shown = stored[::-1] if orientation in _SWAPS_AXES else stored
            if img.format == "TIFF" and img.size != stored:
                # Pillow 13 reports a turned TIFF's size turned before loading and then decodes grey and
                # 16-bit samples into that turned frame (garbage); from the stored size it decodes right
                img._size = stored
            img.load()  # Pillow >= 11 turns a TIFF while loading it and then drops its orientation tag
            img = ImageOps.exif_transpose(img)
            if img.size != shown:
                raise SceneError(f"cannot decode image {path}: decoded {img.size[0]}x{img.size[1]} pixels, but its "
                                 f"header says {shown[0]}x{shown[1]} (EXIF orientation {orientation})")
            if img.mode in _WIDE_MODES:
                return _to_bgr(to_uint8(np.asarray(img), path), rgb=True)
            rgb = np.asarray(img.convert("RGB"))
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise SceneError(f"cannot decode image {path} ({e})") from None
    return np.ascontiguousarray(rgb[..., ::-1])
