"""What `usvc localize` makes of its arguments before it localizes anything: the photos (files, and
folders of images) and the export formats and folder (each photo's camera:
`usvc.relocalize.photo_camera`, shared with `usvc serve`); each wrong value is one line naming the
flag."""

from __future__ import annotations

import argparse
import functools
import logging
from pathlib import Path

from usvc.core.errors import UsvcError
from usvc.relocalize.photo_camera import HEIF_SUFFIXES

# The photos a folder yields (extensions in any case), as usvc.core.images decodes them: by OpenCV,
# else Pillow (a GIF's first frame); AVIF when Pillow has its decoder, HEIC/HEIF with pillow-heif.
FOLDER_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp", ".tif", ".tiff", ".bmp", ".gif")

log = logging.getLogger(__name__)


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


