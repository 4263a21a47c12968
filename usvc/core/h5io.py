"""HDF5 artifacts in and out.

Reading: a missing, corrupt or incomplete file is one UsvcError naming it, never an h5py
traceback. Writing: the file is built in memory and written to disk in one plain write, so a full
disk or a file-size limit is one OSError that the caller's atomic block cleans up after (HDF5
failing mid-file floods stderr and can crash the interpreter).
"""

from __future__ import annotations

import contextlib
import errno
import io
from collections.abc import Iterator
from pathlib import Path

import h5py

from usvc.core.errors import UsvcError


@contextlib.contextmanager
def read_h5(path: str | Path, what: str) -> Iterator[h5py.File]:
    """`h5py.File(path, "r")`; errors while opening or reading inside the block name the file."""
    path = Path(path)
    if not path.is_file():
        raise UsvcError(f"{what} not found: {path}")
    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise UsvcError(f"{path}: cannot read {what}: not an HDF5 file, or corrupt or truncated") from None
    try:
        with h5:
            yield h5
    except UsvcError:
        raise
    except (KeyError, OSError, ValueError, TypeError, IndexError) as exc:
        detail = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        raise UsvcError(f"{path}: {what} is incomplete or corrupt ({detail})") from None


@contextlib.contextmanager
def write_h5(path: str | Path) -> Iterator[h5py.File]:
    """An in-memory HDF5 file that lands at `path` (normally a temporary path inside an atomic
    block) when the block succeeds."""
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as h5:
        yield h5
    write_bytes(Path(path), buffer.getbuffer())


def write_bytes(path: Path, data: bytes | memoryview) -> None:
    """Write a whole file; no space or a file-size limit is a UsvcError naming the file."""
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
            Path(path).unlink(missing_ok=True)
            raise UsvcError(f"cannot write {path}: {exc.strerror} (disk full or a file-size limit)") from None
        raise
