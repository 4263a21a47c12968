"""Decoding photos into pixels: uint8 BGR with the EXIF orientation applied, whatever the format
(JPEG, PNG, TIFF, WebP, BMP, GIF's first frame, AVIF, HEIC/HEIF with pillow-heif installed; 16-bit or
floating-point samples), refusing oversized or truncated files in one line.

The header checks (the MAX_IMAGE_PIXELS limit of what a camera makes, EXIF orientation) are
:mod:`usvc.core.exif`'s. A photo is decoded in full up to MAX_DECODE_PIXELS (300 MB of pixels);
`read_photo` decodes a larger JPEG (a 108 MP phone photo) reduced by 2, 4 or 8, by the JPEG
decoder's own scaling, and says by how much, so that its intrinsics can be scaled with it.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from usvc.core.errors import SceneError
from usvc.core.exif import SWAPS_AXES, apply_orientation, open_checked, orientation_of, read_exif, stored_size

MAX_DECODE_PIXELS = 100_000_000  # decoded in full up to this (300 MB of BGR); larger JPEGs reduced
_REDUCED_FLAGS = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}
HEIF_SUFFIXES = (".heic", ".heif")
NO_HEIF_DECODER = "no HEIC decoder installed (pip install pillow-heif)"


@functools.cache
def heif_decoder() -> bool:
    """Whether HEIC/HEIF photos decode: only with pillow-heif installed (not a dependency), whose
    opener is registered with Pillow by the first call."""
    try:
        from pillow_heif import register_heif_opener
    except ImportError:
        return False
    register_heif_opener()
    return True


@dataclass(frozen=True)
class Photo:
    """A decoded photo: `bgr` is the photo at 1/`reduction` of its `size` (width, height, EXIF
    orientation applied); `reduction` is 1 for all but JPEGs over MAX_DECODE_PIXELS."""

    bgr: np.ndarray
    reduction: int
    size: tuple[int, int]

    def scale(self) -> tuple[float, float]:
        """(x, y) factors from the photo's pixels to the decoded ones."""
        h, w = self.bgr.shape[:2]
        return w / self.size[0], h / self.size[1]


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV logs decoder failures to stderr itself; the caller reports them in one line."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


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


def _over_decode_limit(path: Path, size: tuple[int, int], what: str) -> SceneError:
    return SceneError(f"image {path} is {size[0]}x{size[1]} = {size[0] * size[1] / 1e6:.0f} megapixels, more than "
                      f"the {MAX_DECODE_PIXELS / 1e6:.0f} megapixels decoded in full, {what}")


def _header(path: Path) -> tuple[int, str | None, tuple[int, int]]:
    """(EXIF orientation, Pillow's format name, stored size) from the header, refusing a missing
    file and one over MAX_IMAGE_PIXELS; (1, None, (0, 0)) when Pillow cannot read the header."""
    if not path.is_file():
        raise SceneError(f"image not found: {path}")
    if path.suffix.lower() in HEIF_SUFFIXES:
        heif_decoder()  # Pillow reads HEIC/HEIF once pillow-heif's opener is registered
    try:
        with open_checked(path) as img:
            return orientation_of(read_exif(img)), img.format, stored_size(img)
    except (OSError, UnidentifiedImageError, ValueError):
        return 1, None, (0, 0)


def read_photo(path: str | Path) -> Photo:
    """The photo's pixels as `read_image_bgr` decodes them, except that a JPEG over MAX_DECODE_PIXELS
    is decoded reduced (by the smallest of 2, 4 or 8 that brings it under the limit) instead of
    refused; another format that large is refused in one line."""
    path = Path(path)
    orientation, fmt, stored = _header(path)
    if fmt is None:  # Pillow cannot read its header; OpenCV may still decode it
        bgr = read_image_bgr(path)
        return Photo(bgr, 1, (bgr.shape[1], bgr.shape[0]))
    size = stored[::-1] if orientation in SWAPS_AXES else stored
    if size[0] * size[1] <= MAX_DECODE_PIXELS:
        return Photo(read_image_bgr(path), 1, size)
    if fmt != "JPEG":
        raise _over_decode_limit(path, size, "and only JPEGs decode reduced: downscale it or save it as JPEG")
    if not jpeg_is_complete(path.read_bytes()):
        raise SceneError(f"cannot decode image {path}: truncated or corrupt JPEG (no end-of-image marker)")
    reduction = next((k for k in (2, 4, 8) if size[0] * size[1] / (k * k) <= MAX_DECODE_PIXELS), None)
    if reduction is None:
        raise _over_decode_limit(path, size, "even reduced 8 times: downscale it")
    with _quiet_opencv():
        bgr = cv2.imread(str(path), _REDUCED_FLAGS[reduction] | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise SceneError(f"cannot decode image {path} (a {size[0]}x{size[1]} JPEG, decoded reduced {reduction} times)")
    return Photo(apply_orientation(bgr, orientation), reduction, size)


def read_image_bgr(path: str | Path) -> np.ndarray:
    """uint8 HxWx3 BGR pixels with the EXIF orientation applied (the size oriented_size gives).

    OpenCV decodes, with its own orientation handling off so that every format is turned by the
    same rule. Pillow decodes TIFFs (OpenCV turns them whatever it is told, and OpenCV 5 fails on
    orientations 5-8) and whatever OpenCV cannot. Images over MAX_IMAGE_PIXELS are refused from
    their header; 16-bit samples are scaled to 8 bits (/257) and floating-point ones in 0..1 by 255.
    """
    path = Path(path)
    orientation, fmt, stored = _header(path)
    if stored[0] * stored[1] > MAX_DECODE_PIXELS:
        what = "read it with read_photo (JPEGs decode reduced)" if fmt == "JPEG" else "downscale it"
        raise _over_decode_limit(path, stored, what)
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
        with Image.open(path) as img:  # its size passed open_checked (or Pillow cannot read it)
            stored = stored_size(img)
            shown = stored[::-1] if orientation in SWAPS_AXES else stored
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
        if path.suffix.lower() in HEIF_SUFFIXES and not heif_decoder():
            raise SceneError(f"cannot decode image {path}: {NO_HEIF_DECODER}") from None
        raise SceneError(f"cannot decode image {path} ({e})") from None
    return np.ascontiguousarray(rgb[..., ::-1])
