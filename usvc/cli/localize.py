"""`usvc localize`: each photo's pose against a map, one JSON record a photo (and the files of
--out-dir). Flags, photo paths, headers, intrinsics and --out-dir's writability are checked before
the map is loaded (`photo_args`), so a typo fails in milliseconds, with one line on stderr (exit
1), rather than after the network is built; the heavy modules load only past those checks."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from usvc.cli.photo_args import expand_photos, output_formats
from usvc.relocalize.photo_camera import UnreadablePhoto, answer_record, photo_camera, split_camera
from usvc.core.errors import UsvcError
from usvc.pipeline import threads
from usvc.relocalize.options import MAX_ERROR_PX, REFERENCE_SHORT_SIDE, RelocalizeOptions

if TYPE_CHECKING:
    from usvc.core.scene import Camera
    from usvc.relocalize.relocalizer import Relocalizer

log = logging.getLogger("usvc")

Found = tuple["Camera | None", str, str]  # a photo's camera (None: estimated), its source, the note naming it


def localize(args: argparse.Namespace) -> int:
    """Localize each photo.

    A photo that is unreadable (a header that cannot be read, a decompression bomb, a truncated
    JPEG) gets its own record with "error" and the others go on; the exit status is then 1 (when no
    photo can be read at all, that is the one error line). --out-dir files are written only at the
    end, each atomically.
    """
    from usvc.cli.exports import export

    formats, photos, cameras = _photos(args)
    relocalizer = _relocalizer(args)
    records, posed, errors = _report(args, photos, cameras, _estimates(args, relocalizer, photos, cameras))
    if formats:
        export(Path(args.out_dir), formats, records, posed)
    if args.json_list:
        print(json.dumps(records, indent=2))
    return 1 if errors else 0  # every photo has its record; the status says some could not be read


def _photos(args: argparse.Namespace) -> tuple[list[str], list[tuple[str, Path]], list[Found | UnreadablePhoto]]:
    """The export formats, the photos (name, path) and each one's camera (or why it cannot be read);
    a UsvcError when no photo can be read at all."""
    from usvc.cli.exports import check_names

    camera = None
    photo_args = list(args.photos)
    if args.camera is not None:
        model, params, swallowed = split_camera(args.camera)
        camera, photo_args = (model, params), swallowed + photo_args
    formats = output_formats(args)
    photos = expand_photos(photo_args)
    if formats:
        check_names(formats, [n for n, _ in photos], [p for _, p in photos])
    cameras: list[Found | UnreadablePhoto] = []
    for name, path in photos:
        try:
            cameras.append(photo_camera(args, camera, name, path))
        except UnreadablePhoto as err:  # that photo's failure; the others go on
            cameras.append(err)
    unreadable = [c for c in cameras if isinstance(c, UnreadablePhoto)]
    if len(unreadable) == len(photos):
        raise UsvcError(str(unreadable[0]) if len(photos) == 1 else
                        f"none of the {len(photos)} photos can be read; the first: {unreadable[0]}")
    return formats, photos, cameras


def _relocalizer(args: argparse.Namespace) -> Relocalizer:
    """The relocalizer the flags ask for, their values checked first; the threads shared among
    --workers photos at a time."""
    if not 0.0 < args.max_error_px <= MAX_ERROR_PX:
        raise UsvcError(f"--max-error-px {args.max_error_px:g}: must be in (0, {MAX_ERROR_PX:g}] (px at a "
                        f"{REFERENCE_SHORT_SIDE} px short side; larger thresholds accept any pose)")

    from usvc.relocalize.photo_batch import check_workers, threads_per_query
    from usvc.relocalize.query_input import check_device
    from usvc.relocalize.relocalizer import Relocalizer

    try:
        check_workers(args.workers)
    except UsvcError:
        raise UsvcError(f"--workers {args.workers}: must be a whole number >= 1") from None
    # several photos at a time: the threads are shared among them (each query gets threads // workers)
    threads.apply(threads_per_query(args.threads, args.workers))
    device = check_device(args.device)
    refine = "none" if args.no_refine else args.refine
    options = RelocalizeOptions(backend=args.backend, max_error_px=args.max_error_px, refine=refine,
                                prior=args.prior, features_final=args.final, precision=args.precision)
    if args.min_confidence is not None:
        if not 0.0 <= args.min_confidence <= 1.0:
            raise UsvcError(f"--min-confidence {args.min_confidence:g}: must be in [0, 1]")
        options = replace(options, min_confidence=args.min_confidence)
    if args.focal_tolerance is not None:
        if args.focal_tolerance < 0:
            raise UsvcError(f"--focal-tolerance {args.focal_tolerance:g}: must be >= 0 (0: no check)")
        options = replace(options, focal_tolerance=args.focal_tolerance)
    return Relocalizer(args.map, args.encoder_weights, options, device=device, landmarks=args.landmarks)


def _estimates(args: argparse.Namespace, relocalizer: Relocalizer, photos: list[tuple[str, Path]],
               cameras: list[Found | UnreadablePhoto]) -> Iterator[Any]:
    """Each photo's estimate, or the UsvcError that is its failure, in the photos' order: --workers
    at a time, on threads (one at a time: the next photo decoded meanwhile; several: each query
    decodes its own) or with --processes in worker processes."""
    from usvc.cli.photo_prefetch import decoded_ahead
    from usvc.core.images import read_photo
    from usvc.relocalize.photo_batch import in_order, threads_per_query

    readable = [None if isinstance(c, UnreadablePhoto) else p for (_, p), c in zip(photos, cameras)]
    decoded = decoded_ahead(readable) if args.workers == 1 else iter([None] * len(photos))

    def answer(item: tuple) -> Any:
        """The photo's estimate, or the UsvcError that is its failure (one unreadable photo is that
        photo's failure, not the end of the others')."""
        (name, path), found, photo = item
        try:
            if isinstance(found, UnreadablePhoto):
                raise found
            cam, source, note = found
            # read as the relocalizer reads a path (EXIF orientation applied, huge JPEGs reduced)
            image = photo.result() if photo is not None else read_photo(path)
            return relocalizer.localize(image, cam, **({"intrinsics_source": note} if note else {}))
        except UsvcError as err:
            return err

    if args.processes and args.workers > 1:  # each process reads its photos as answer() reads them
        from usvc.relocalize.photo_processes import in_processes

        work = (found if isinstance(found, UnreadablePhoto) else
                (path, found[0], {"intrinsics_source": found[2]} if found[2] else {})
                for (_, path), found in zip(photos, cameras))
        return in_processes(type(relocalizer), relocalizer.args, work, args.workers,
                            threads_per_query(args.threads, args.workers), errors="return")
    return in_order(answer, zip(photos, cameras, decoded), args.workers)


def _report(args: argparse.Namespace, photos: list[tuple[str, Path]], cameras: list[Found | UnreadablePhoto],
            estimates: Iterator[Any]) -> tuple[list[dict[str, Any]], list[Any], int]:
    """Each photo's record, printed as it comes (unless --json-list), the posed photos for the
    exports, and how many photos failed."""
    from tqdm import tqdm

    from usvc.cli.exports import Posed

    records: list[dict[str, Any]] = []
    posed: list[Posed] = []
    bar = tqdm(total=len(photos), desc="localize", unit="photo", file=sys.stderr,
               disable=len(photos) < 2 or not sys.stderr.isatty())
    errors = 0
    for ((name, path), found), estimate in zip(zip(photos, cameras), estimates):
        bar.update()
        if isinstance(estimate, UsvcError):
            errors += 1
            log.error("%s: %s", name, estimate)
            record = {"name": name, "success": False, "error": str(estimate)}
        else:
            cam, source, note = found
            record = answer_record(name, estimate, source, note)
            if estimate.success:
                used = estimate.camera or cam
                if used is None:
                    raise UsvcError(f"{name}: the relocalizer returned a pose without a camera")
                posed.append(Posed(name, path, used, estimate.R, estimate.t))
        records.append(record)
        if not args.json_list:
            tqdm.write(json.dumps(record), file=sys.stdout)
            sys.stdout.flush()
    bar.close()
    return records, posed, errors
