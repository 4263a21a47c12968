"""What `usvc localize` makes of its arguments before it localizes anything: the photos (files, and
folders of images), each photo's camera (--focal, --intrinsics, --camera, else its EXIF focal
length, else none: estimated with the pose) and the export formats and folder; each wrong value is
one line naming the flag."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from usvc.core.errors import SceneError, UsvcError

if TYPE_CHECKING:
    from usvc.core.scene import Camera

CAMERA_PARAMS = {"SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
                 "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2",
                 "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4", "FULL_OPENCV": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6"}



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


def expand_photos(args: list[str]) -> list[tuple[str, Path]]:
    """(name, path) per photo: files as given, folders as their images sorted by name."""
    from usvc.prepare.importers.common import IMAGE_SUFFIXES

    photos: list[tuple[str, Path]] = []
    for arg in args:
        path = Path(arg)
        if path.is_dir():
            images = sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                            key=lambda p: p.name)
            if not images:
                raise UsvcError(f"folder {arg} has no images ({' '.join(IMAGE_SUFFIXES)})")
            photos += [(str(p), p) for p in images]
        elif path.is_file():
            photos.append((arg, path))
        else:
            raise UsvcError(f"image not found: {arg}")
    if not photos:
        raise UsvcError("no photos given")
    return photos


def output_formats(args: argparse.Namespace) -> list[str]:
    from usvc.relocalize.exports import FORMATS

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
