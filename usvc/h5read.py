"""Opening an artifact's HDF5 file for reading: a missing, corrupt or incomplete file is one
UsvcError naming it, never an h5py traceback."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import h5py

from usvc.errors import UsvcError


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
