"""HDF5 artifacts in and out.

Reading: a missing, corrupt or incomplete file is one UsvcError naming it, never an h5py
traceback. Writing: the file is built in memory and written to disk in one plain write, so a full
disk or a file-size limit is one OSError that the caller's atomic block cleans up after (HDF5
failing mid-file floods stderr and can crash the interpreter).

Self-description: a writer passes its file's `format` name, `version` and a schema (dataset path
-> `Field`); every dataset in the file then carries `units`, `description` and, where it has
one, `frame` attributes, and a dataset the schema does not describe is a programming error
(ValueError) rather than an undocumented column. docs/artifacts.md lists the same fields.
"""

from __future__ import annotations

import contextlib
import errno
import io
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
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


@dataclass(frozen=True)
class Field:
    """What one dataset holds, written as its attributes.

    units: "px", "deg", "s", "scene units" (world length; times the scene's metric_scale gives
    metres), "1" (unitless: ratios, counts, indices, flags, names), or a short list where the
    columns differ (camera parameters).
    frame: "world", "camera", "image", or "A->B" for a transform from frame A to frame B; None
    where no frame applies (names, indices, features).
    """

    units: str
    description: str
    frame: str | None = None


# A schema maps a dataset's path in the file to its Field; "group/*" describes every dataset
# directly inside `group` (numbered datasets such as scene.h5's depth/<i>).
Schema = Mapping[str, Field]


def schema_field(schema: Schema, name: str) -> Field | None:
    """The Field of dataset `name` (a path inside the file, no leading slash), or None."""
    if name in schema:
        return schema[name]
    group = name.rsplit("/", 1)[0] if "/" in name else ""
    return schema.get(f"{group}/*" if group else "*")


def describe_datasets(h5: h5py.File, schema: Schema, where: str = "") -> None:
    """Write `units`, `description` (and `frame`) on every dataset of `h5` from `schema`."""
    datasets: list[str] = []
    h5.visititems(lambda name, obj: datasets.append(name) if isinstance(obj, h5py.Dataset) else None)
    undocumented = [name for name in datasets if schema_field(schema, name) is None]
    if undocumented:
        raise ValueError(f"{where or h5.filename}: dataset(s) {undocumented} missing from the writer's schema")
    for name in datasets:
        doc = schema_field(schema, name)
        assert doc is not None
        attrs = h5[name].attrs
        attrs["units"], attrs["description"] = doc.units, doc.description
        if doc.frame is not None:
            attrs["frame"] = doc.frame


@contextlib.contextmanager
def write_h5(path: str | Path, schema: Schema | None = None, file_format: str | None = None,
             version: int | None = None) -> Iterator[h5py.File]:
    """An in-memory HDF5 file that lands at `path` (normally a temporary path inside an atomic
    block) when the block succeeds.

    With `schema`, every dataset written in the block gets its attributes (`describe_datasets`)
    when the block ends; `file_format` and `version` become the file's `format` and `version`
    attributes.
    """
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as h5:
        yield h5
        if file_format is not None:
            h5.attrs["format"] = file_format
        if version is not None:
            h5.attrs["version"] = version
        if schema is not None:
            describe_datasets(h5, schema, str(path))
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
