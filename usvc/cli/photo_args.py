"""What `usvc localize` makes of its arguments before it localizes anything: the photos (files, and
folders of images), each photo's camera (--focal, --intrinsics, --camera, else its EXIF focal
length, else none: estimated with the pose) and the export formats and folder; each wrong value is
one line naming the flag."""

from __future__ import annotations

import argparse
import functools
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from usvc.core.errors import SceneError, UsvcError

if TYPE_CHECKING:
    from usvc.core.scene import Camera

CAMERA_PARAMS = {"SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
                 "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2",
                 "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4", "FULL_OPENCV": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6"}
# The photos a folder yields (extensions in any case), as usvc.core.images decodes them: by OpenCV,
# else Pillow (a GIF's first frame); AVIF when Pillow has its decoder, HEIC/HEIF with pillow-heif.
FOLDER_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".bmp", ".gif")
HEIF_SUFFIXES = (".heic", ".heif")  # as usvc.core.images.HEIF_SUFFIXES

log = logging.getLogger(__name__)


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


@functools.cache
def folder_suffixes() -> tuple[str, ...]:
    """The extensions (lower case) of the files a folder yields: FOLDER_SUFFIXES, with .avif when
    Pillow decodes AVIF and .heic/.heif when pillow-heif is installed (found without importing
    OpenCV, so that a wrong argument still fails at once)."""
    import importlib.util

    from PIL import features

    try:
        avif = bool(features.check("avif"))
    except (ValueError, KeyError):  # a Pillow that does not know the feature
        avif = False
    heif = importlib.util.find_spec("pillow_heif") is not None
    return FOLDER_SUFFIXES + (".avif",) * avif + HEIF_SUFFIXES * heif


def skip_reason(path: Path) -> str | None:
    """Why a folder's entry (not a subfolder) is not one of its photos; None when it is one."""
    if not path.is_file():
        return "not a regular file (a broken link?)"
    suffix = path.suffix.lower()
    if suffix in folder_suffixes():
        return None
    if suffix in HEIF_SUFFIXES:
        from usvc.core.images import NO_HEIF_DECODER

        return NO_HEIF_DECODER
    what = f"{path.suffix} files" if path.suffix else "files without an extension"
    return (f"{what} are not listed (a folder yields {' '.join(folder_suffixes())}, in any case; "
            "name the file itself to try it)")


def folder_photos(folder: Path) -> tuple[list[Path], list[tuple[Path, str]]]:
    """A folder's photos sorted by name, and the files it skips with the reason for each."""
    photos: list[Path] = []
    skipped: list[tuple[Path, str]] = []
    for p in sorted(folder.iterdir(), key=lambda p: p.name):
        if p.is_dir():
            continue  # not recursive: a subfolder is not a file of this folder
        why = skip_reason(p)
        if why is None:
            photos.append(p)
        else:
            skipped.append((p, why))
    return photos, skipped


def expand_photos(args: list[str]) -> list[tuple[str, Path]]:
    """(name, path) per photo: files as given, folders as their photos sorted by name (the formats
    of folder_suffixes, any case); each other file of a folder is named in one warning line with
    why it is skipped (in the error instead when the folder has no photo)."""
    photos: list[tuple[str, Path]] = []
    for arg in args:
        path = Path(arg)
        if path.is_dir():
            images, skipped = folder_photos(path)
            if not images:
                listed = "; ".join(f"{p.name} ({why})" for p, why in skipped[:3])
                more = f"; and {len(skipped) - 3} more" if len(skipped) > 3 else ""
                raise UsvcError(f"folder {arg} has no images ({' '.join(folder_suffixes())}, in any case)"
                                + (f"; skipped {listed}{more}" if skipped else ""))
            for p, why in skipped:
                log.warning("skipped %s: %s", p, why)
            photos += [(str(p), p) for p in images]
        elif path.is_file():
            photos.append((arg, path))
        else:
            raise UsvcError(f"image not found: {arg}")
    if not photos:
        raise UsvcError("no photos given")
    if any(p.suffix.lower() in HEIF_SUFFIXES for _, p in photos):
        from usvc.core.images import heif_decoder

        heif_decoder()  # registers pillow-heif with Pillow, which reads the headers (photo_camera)
    return photos


def output_formats(args: argparse.Namespace) -> list[str]:
    from usvc.cli.exports import FORMATS

    if args.out_dir is None:
        if args.format:
            raise UsvcError("--format needs --out-dir")
        return []
    chosen = [f.strip() for item in args.format or [",".join(FORMATS)] for f in item.split(",") if f.strip()]
    if not chosen:
        raise UsvcError(f"--format {','.join(args.format)!r} names no format; valid: {', '.join(FORMATS)}")
    for f in chosen:
        if f not in FORMATS:
            raise UsvcError(f"--format: unknown format {f!r}; known: {', '.join(FORMATS)}")
    if Path(args.out_dir).exists() and not Path(args.out_dir).is_dir():
        raise UsvcError(f"--out-dir {args.out_dir} exists and is not a folder")
    check_out_dir(Path(args.out_dir))
    return list(dict.fromkeys(chosen))


def check_out_dir(folder: Path) -> None:
    """--out-dir must be a folder this user can write in, or one it can create: checked before any
    photo is localized, so a read-only folder fails now, not after the whole batch."""
    import tempfile

    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UsvcError(f"--out-dir {folder}: {existing} is a file, not a folder")
    try:  # the files are written as temporary siblings, then renamed: try that much
        with tempfile.NamedTemporaryFile(dir=existing, prefix=".usvc-write-test-"):
            pass
    except OSError as e:
        what = "folder" if existing == folder else f"folder {existing} (where it would be created)"
        raise UsvcError(f"--out-dir {folder}: cannot write in the {what}: {e.strerror or e}") from None


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
