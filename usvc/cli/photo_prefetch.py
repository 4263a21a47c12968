"""Photos decoded one ahead: while one photo is localized, the next is read on a second thread
(`read_photo`: JPEG decoding, EXIF orientation, huge JPEGs reduced), so a folder of photos does not
wait on decoding between queries."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from usvc.core import images


def decoded_ahead(paths: list[Path | None]) -> Iterator[Future | None]:
    """Each photo's `read_photo` as a future, the next one already submitted when a photo is handed
    out; its result raises what `read_photo` raised. None in `paths` (a photo already known to be
    unreadable) gives None and decodes nothing. A photo is not kept once handed out."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="usvc-decode") as pool:
        def submit(path: Path | None) -> Future | None:
            return pool.submit(images.read_photo, path) if path is not None else None

        ahead = [submit(p) for p in paths[:1]]
        for k in range(len(paths)):
            if k + 1 < len(paths):
                ahead.append(submit(paths[k + 1]))
            yield ahead[k]
            ahead[k] = None
