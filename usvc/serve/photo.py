"""An uploaded photo, from bytes to the record `usvc localize --format jsonl` writes.

Its header is read from memory before anything is decoded (format, megapixels). The bytes are
then written to a private temporary file, and that file goes the very way a photo path goes
through `usvc localize` (its camera and EXIF focal length from the header, `read_photo`: EXIF
orientation applied, truncated JPEGs refused, huge JPEGs decoded reduced), so the answer is bit
for bit the command's and `Relocalizer.localize`'s on the same file. The file is removed when the
request ends; its path is never a client's.
"""

from __future__ import annotations

import io
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any

from PIL import Image, UnidentifiedImageError

from usvc.core.errors import UsvcError
from usvc.core.images import read_photo
from usvc.relocalize.photo_camera import answer_record
from usvc.relocalize.relocalizer import Relocalizer
from usvc.serve.errors import ApiError
from usvc.serve.intrinsics import PhotoIntrinsics, UnreadablePhoto, camera_of, plain

# Pillow's format name -> the suffix the temporary file gets (the decoders choose by content,
# HEIF by suffix too)
SUFFIXES = {"JPEG": ".jpg", "MPO": ".jpg", "PNG": ".png", "WEBP": ".webp", "TIFF": ".tif", "BMP": ".bmp",
            "GIF": ".gif", "AVIF": ".avif", "HEIF": ".heic"}
INTRINSICS_WORDS = ("intrinsic", "focal", "principal point", "camera")


def check_header(data: bytes, max_megapixels: float) -> str:
    """The suffix of the photo's format, from its header alone; 400 for what is not a photo, 413
    for more pixels than allowed (nothing is decoded here)."""
    if not data:
        raise ApiError("bad_photo", "the photo is empty (0 bytes)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as img:  # the header only
                fmt, (w, h) = img.format, img.size
    except Image.DecompressionBombError:
        raise ApiError("too_many_pixels", f"the photo's header claims more pixels than the "
                       f"{max_megapixels:g} megapixels allowed") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        if isinstance(e, UnidentifiedImageError):
            why = "not an image usvc reads"
        else:
            why = f"its header cannot be read ({' '.join(str(e).split())[:120]})"
        raise ApiError("bad_photo", f"the photo is {why} (JPEG, PNG, WebP, TIFF, BMP, GIF; AVIF, HEIC where "
                       "decoders are installed)") from None
    if fmt not in SUFFIXES:
        raise ApiError("bad_photo", f"photos in {fmt} format are not taken; send JPEG, PNG, WebP, TIFF, BMP or GIF")
    if w * h > max_megapixels * 1e6:
        raise ApiError("too_many_pixels", f"the photo is {w}x{h} = {w * h / 1e6:.1f} megapixels, more than the "
                       f"{max_megapixels:g} allowed")
    return SUFFIXES[fmt]


def localize_photo(relocalizer: Relocalizer, data: bytes, suffix: str, given: PhotoIntrinsics, name: str,
                   workdir: Path) -> dict[str, Any]:
    """The record of `usvc localize` for the photo (in a worker thread). Its intrinsics and pixels
    are found as the command finds them; a photo or intrinsics it refuses raise ApiError 400."""
    fd, tmp = tempfile.mkstemp(suffix=suffix, prefix="upload-", dir=workdir)
    path = Path(tmp)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)

        def clean(message: str) -> str:  # the temporary path is no business of the client's
            return plain(message.replace(str(path), name).replace(path.name, name))

        try:
            cam, source, note = camera_of(given, name, path)
        except UnreadablePhoto as err:
            raise ApiError("bad_photo", clean(str(err))) from None
        except UsvcError as err:
            raise ApiError("bad_intrinsics", clean(str(err))) from None
        try:
            image = read_photo(path)  # as the command reads it (EXIF orientation applied, huge JPEGs reduced)
            estimate = relocalizer.localize(image, cam, **({"intrinsics_source": note} if note else {}))
        except UsvcError as err:
            message = clean(str(err))
            about_camera = cam is not None and any(w in message.lower() for w in INTRINSICS_WORDS)
            raise ApiError("bad_intrinsics" if about_camera else "bad_photo", message) from None
        return answer_record(name, estimate, source, note)
    finally:
        path.unlink(missing_ok=True)
